"""Process-level settings: glibc's allocator modes (each checked in a fresh process: they are process-wide)."""

import ctypes
import subprocess
import sys

import pytest

from dider.perf import ALLOCATORS, tune_allocator
from dider.run import validate_config
from dider.validation import ConfigError

# A 64 MiB tensor, above glibc's largest mmap threshold (32 MiB): is it a fresh mmap (counted in mallinfo2's
# hblks, the chunks mmap serves) or heap memory that a later tensor reuses?
PROBE = """
import ctypes, sys, torch
from dider.perf import tune_allocator
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks "
                                                "fordblks keepcost").split()]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info
print(tune_allocator(sys.argv[1]))
before = libc.mallinfo2().hblks  # chunks mmapped at start-up (imports) stay so
x = torch.ones(16 * 2**20)
print(libc.mallinfo2().hblks - before)
"""


def _has_mallinfo2() -> bool:
    try:
        return sys.platform.startswith("linux") and hasattr(ctypes.CDLL("libc.so.6"), "mallinfo2")
    except OSError:
        return False


@pytest.mark.skipif(not _has_mallinfo2(), reason="glibc >= 2.33 (mallinfo2) on Linux only")
@pytest.mark.parametrize("mode", ALLOCATORS)
def test_allocator_modes_decide_where_large_tensors_live(mode):
    """heap: no large tensor is a fresh mmap (freed memory is reused, no page faults); thresholds and system:
    tensors above 32 MiB still are."""
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True).stdout
    applied, mmapped = out.split()
    assert applied == str(mode != "system")
    assert (int(mmapped) == 0) is (mode == "heap")


def test_bad_allocator_is_named(make_cfg):
    with pytest.raises(ValueError, match=r"allocator='fast': expected one of \['heap', 'thresholds', 'system'\]"):
        tune_allocator("fast")
    with pytest.raises(ConfigError, match="allocator='fast'"):
        validate_config(make_cfg(["allocator=fast"]))
