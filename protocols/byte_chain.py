"""The chain of messages in a block of log bytes, found without a Python step per message.

A log reader finds each message where the one before it ends, so which candidate positions
(header bytes found by a vectorized scan, some of them inside other messages' payloads) start
real messages is a walk. Given, for every candidate, the candidate its message leads to
(``succ``, always a later one, or -1 where the walk stops), the walk from ``first`` is the
greatest set ``C`` with ``C = {first} ∪ succ(C)``: every member other than ``first`` has a
predecessor in ``C``, and following predecessors back (to ever smaller indices) ends at
``first``. Iterating ``C ← {first} ∪ succ(C)`` from all candidates shrinks to it, each round
removing the heads of chains no member leads to; false candidates are rare and their chains
short, so a few rounds do. Bytes made to defeat that (long chains beside the real one) fall back
to the walk itself after :data:`ROUNDS` rounds.
"""

from __future__ import annotations

import numpy as np

STRUCT_TO_NUMPY = {
    "b": "i1",
    "B": "u1",
    "h": "<i2",
    "H": "<u2",
    "i": "<i4",
    "I": "<u4",
    "q": "<i8",
    "Q": "<u8",
    "e": "<f2",
    "f": "<f4",
    "d": "<f8",
}
"""Python ``struct`` codes (little-endian, packed) as numpy types: the messages' own struct formats
(pymavlink's ``DFFormat.msg_struct``, a MAVLink message's ``unpacker``) as structured dtypes."""

ROUNDS = 12
"""Rounds of the set iteration before :func:`chain` walks instead (a round costs about as much as
walking a tenth of the candidates in Python)."""


def chain(first: int, succ: np.ndarray, rounds: int = ROUNDS) -> np.ndarray:
    """Indices (increasing) of the candidates the walk from ``first`` visits, ``first`` included.

    ``succ[i] > i`` is the candidate after ``i``, or -1 where the walk stops; ``first`` < 0: none.
    """
    n = succ.size
    if first < 0:
        return np.zeros(0, dtype=np.int64)
    on = np.ones(n, dtype=bool)
    for _ in range(rounds):
        nxt = succ[on]
        new = np.zeros(n, dtype=bool)
        new[nxt[nxt >= 0]] = True
        new[first] = True
        if np.array_equal(new, on):
            return np.flatnonzero(on)
        on = new
    return walk(first, succ)


def walk(first: int, succ: np.ndarray) -> np.ndarray:
    """The same walk, one step at a time (:func:`chain`'s fallback and its test oracle)."""
    step = succ.tolist()
    out = []
    i = first
    while i >= 0:
        out.append(i)
        i = step[i]
    return np.array(out, dtype=np.int64)
