"""Replay's batches reuse the heap: glibc's malloc keeps a batch's temporaries of a few MB for the
next batch instead of mapping and faulting their pages in afresh (service.commands.replay)."""

import os
import subprocess
import sys

import pytest

from service.commands import replay

GLIBC = (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")

_MAPPED = """
import ctypes, sys
import numpy as np


class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost",
    )]


libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
if sys.argv[1] == "set":
    from service.commands.replay import keep_batch_temporaries_on_heap
    assert keep_batch_temporaries_on_heap()
batch = np.ones(1 << 19)  # 4 MB: a batch's temporary
print(libc.mallinfo2().hblkhd >= batch.nbytes)  # bytes in blocks mapped from the kernel
"""


@pytest.mark.skipif(not GLIBC, reason="the thresholds are glibc's malloc's")
def test_a_batch_temporary_comes_from_the_heap_not_a_fresh_mapping():
    # glibc's start threshold (128 kB) held, as in a process that never freed a larger mapped block:
    # a 4 MB temporary is a mapping of its own, unmapped when freed and faulted in afresh at the
    # next batch. Set, it comes from the heap, which keeps it for the next batch.
    env = dict(os.environ, GLIBC_TUNABLES="glibc.malloc.mmap_threshold=131072")
    mapped = {}
    for mode in ("held", "set"):
        out = subprocess.run(
            [sys.executable, "-c", _MAPPED, mode], env=env, capture_output=True, text=True
        )
        if "mallinfo2" in out.stderr:
            pytest.skip("glibc older than 2.33: no mallinfo2 to read the mapped blocks")
        assert out.returncode == 0, out.stderr
        mapped[mode] = out.stdout.strip()
    assert mapped == {"held": "True", "set": "False"}


def test_other_c_libraries_are_left_as_they_are(monkeypatch):
    def not_glibc(name):
        raise ValueError("unrecognized configuration name")

    monkeypatch.setattr(os, "confstr", not_glibc)
    assert replay.keep_batch_temporaries_on_heap() is False
    monkeypatch.setattr(os, "confstr", lambda name: None)
    assert replay.keep_batch_temporaries_on_heap() is False
