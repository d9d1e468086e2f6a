"""The messages of a ULog data section found in bulk, for :class:`protocols.ulog.UlogImuStream`.

The stream reads a message (``uint16 msg_size, uint8 msg_type``, the payload) where the one before
it ends, one Python step per message: 0.5 µs each, most of reading a ULog whose IMU topics are
then decoded with numpy. Which positions of a buffer start the messages the stream would read in a
row is the walk of :func:`protocols.byte_chain.chain`: the candidates are the positions whose header
the stream takes (a size of 1 … :data:`protocols.ulog.MAX_MESSAGE_BYTES`, a type letter ``A`` … ``Z``),
each leading to the one where its message ends. The run stops before anything the stream does one
step at a time: a header it takes as corrupt, a subscription (``A``: it changes what later data
messages are), a message the buffer does not hold whole, a data message too short for its id, or
one starting past ``stop``.
"""

from __future__ import annotations

import numpy as np

from protocols.byte_chain import chain

SUBSCRIBE = ord("A")
DATA = ord("D")
DATA_MIN_SIZE = 2
"""A data message's ``uint16 msg_id``: one shorter is corrupt (the stream's loop says so)."""


def message_run(
    buf: bytes, pos: int, stop: int, max_size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions, types, sizes) of the messages read in a row from ``pos`` (module docstring):
    each starting before ``stop``, a size of 1 … ``max_size``, whole in ``buf``, none a subscription."""
    d = np.frombuffer(buf, dtype=np.uint8)
    end = min(stop, d.size - 3)
    if end <= pos:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.uint8), np.zeros(0, dtype=np.int64)
    n = end - pos
    head = d[pos : end + 2]
    kind = head[2 : n + 2]
    # A type letter B … Z (A, a subscription, ends a run): one subtraction that wraps the bytes
    # below B past Z (uint8) and one comparison, then the size's high byte (max_size < 2**16
    # leaves few positions to look at closely): four passes over the bytes, not seven.
    maybe = kind - (SUBSCRIBE + 1) <= ord("Z") - (SUBSCRIBE + 1)
    maybe &= head[1 : n + 1] <= max_size >> 8
    at = np.flatnonzero(maybe)
    size = head[at].astype(np.int64) | (head[at + 1].astype(np.int64) << 8)
    good = (size > 0) & (size <= max_size) & (pos + at + 3 + size <= d.size)
    good &= (size >= DATA_MIN_SIZE) | (kind[at] != DATA)
    at, size = at[good], size[good]
    if not at.size or at[0] != 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.uint8), np.zeros(0, dtype=np.int64)
    nxt = at + 3 + size
    # Looked up only where a message ends on a byte the scan kept (most candidates inside payloads
    # end elsewhere): the binary search for half the candidates.
    look = np.flatnonzero(maybe[np.minimum(nxt, n - 1)] & (nxt < n))
    k = np.searchsorted(at, nxt[look])
    found = k < at.size
    found[found] = at[k[found]] == nxt[look[found]]
    succ = np.full(at.size, -1, dtype=np.int64)
    succ[look[found]] = k[found]
    path = chain(0, succ)
    starts = pos + at[path]
    return starts, d[starts + 2], size[path]
