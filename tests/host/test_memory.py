"""`host.memory.fix_mmap_threshold` (issue 34): after it, a large block freed and allocated again is
still served by its own mmap (glibc's ``mallinfo2().hblkhd`` counts it) instead of from the heap,
where its pages would stay resident after the next free. Each case in a fresh process: glibc's
threshold is process-wide and only moves up."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")

PROBE = textwrap.dedent("""
    import ctypes, sys
    libc = ctypes.CDLL("libc.so.6")
    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                    "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    SETUP
    size = 4 << 20
    libc.free(libc.malloc(size))         # glibc raises its threshold to 4 MiB here, unless fixed
    before = libc.mallinfo2().hblkhd
    p = libc.malloc(size)
    print(libc.mallinfo2().hblkhd - before)   # bytes mmapped for the second block
    libc.free(p)
""")


def _mmapped_bytes(setup: str, env=None) -> int:
    r = subprocess.run([sys.executable, "-c", PROBE.replace("SETUP", setup)], capture_output=True,
                       text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr
    return int(r.stdout.split()[-1])


def _glibc() -> bool:
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return False
    return True


@pytest.mark.skipif(not _glibc(), reason="needs glibc >= 2.33 (mallinfo2)")
def test_a_large_block_stays_mmapped_after_one_was_freed():
    assert _mmapped_bytes("pass") == 0  # glibc's dynamic threshold: the heap serves it
    assert _mmapped_bytes("from host.memory import fix_mmap_threshold; assert fix_mmap_threshold()") >= 4 << 20


@pytest.mark.skipif(not _glibc(), reason="needs glibc >= 2.33 (mallinfo2)")
def test_every_capsheet_command_fixes_it_and_a_users_choice_stands():
    import os
    via_cli = "from host.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass"
    assert _mmapped_bytes(via_cli) >= 4 << 20
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_=str(64 << 20))  # the user's: above the block
    assert _mmapped_bytes(via_cli, env=env) == 0
