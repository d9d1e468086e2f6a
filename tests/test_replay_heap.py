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


libc = ctypes.CDLL(None)
# mallinfo2 (glibc 2.33 on) counts in size_t, mallinfo before it in int: either holds 4 MB.
info = getattr(libc, "mallinfo2", None) or libc.mallinfo
field = ctypes.c_size_t if info.__name__ == "mallinfo2" else ctypes.c_int


class MallInfo(ctypes.Structure):
    _fields_ = [(name, field) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost",
    )]


info.restype = MallInfo
if sys.argv[1] == "held":  # glibc's start threshold, as in a process that never raised it
    assert libc.mallopt(-3, 131072)  # M_MMAP_THRESHOLD
else:
    from service.commands.replay import keep_batch_temporaries_on_heap
    assert keep_batch_temporaries_on_heap() is (sys.argv[1] == "set")
batch = np.ones(1 << 19)  # 4 MB: a batch's temporary
print(info().hblkhd >= batch.nbytes)  # bytes in blocks mapped from the kernel
"""


@pytest.mark.skipif(not GLIBC, reason="the thresholds are glibc's malloc's")
def test_a_batch_temporary_comes_from_the_heap_not_a_fresh_mapping():
    # glibc's start threshold (128 kB) held, as in a process that never freed a larger mapped block:
    # a 4 MB temporary is a mapping of its own, unmapped when freed and faulted in afresh at the
    # next batch. Set, it comes from the heap, which keeps it for the next batch.
    assert _mapped("held", {}) == "True"
    assert _mapped("set", {}) == "False"


def _mapped(mode: str, settings: dict[str, str]) -> str:
    """Whether a 4 MB temporary is a mapping of its own, in a child with these ``settings``."""
    env = {k: v for k, v in os.environ.items() if k not in replay.USER_MALLOC_SETTINGS}
    env.pop("GLIBC_TUNABLES", None)
    out = subprocess.run(
        [sys.executable, "-c", _MAPPED, mode],
        env={**env, **settings},
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.skipif(not GLIBC, reason="the thresholds are glibc's malloc's")
@pytest.mark.parametrize(
    "settings",
    [
        {"MALLOC_MMAP_THRESHOLD_": "131072"},
        {"GLIBC_TUNABLES": "glibc.malloc.mmap_threshold=131072"},
    ],
    ids=["environment", "tunables"],
)
def test_thresholds_the_user_set_stand(settings):
    # A device short of memory may ask glibc for small mappings and eager trimming: replay does
    # not set its own over them, and the temporary stays a mapping, as the user asked.
    assert _mapped("user", settings) == "True"


def test_other_c_libraries_are_left_as_they_are(monkeypatch):
    def not_glibc(name):
        raise ValueError("unrecognized configuration name")

    monkeypatch.setattr(os, "confstr", not_glibc)
    assert replay.keep_batch_temporaries_on_heap() is False
    monkeypatch.setattr(os, "confstr", lambda name: None)
    assert replay.keep_batch_temporaries_on_heap() is False
