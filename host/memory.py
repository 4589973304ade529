"""glibc's allocator in processes that run for days (issue 34).

glibc serves a large allocation (128 KiB and up, at first) with its own ``mmap`` and gives the pages
back at ``free``. But it *raises* that threshold to the size of every mmapped block freed (up to 32
MiB on 64-bit), so after a few megabyte-sized buffers come and go — an MCAP chunk and its zstd
context when a recording starts its next file, numpy temporaries — later ones of that size come
from the heap, whose free space is returned to the system only from its top: the resident size
steps up and stays. Measured with ``benchmarks/bench_soak.py --duration 420 --split-duration 100``
(14x14 at 145 Hz, recording, a file every 100 s): the host grew 94.7 → 128.9 MB, 5.3 MB over the
run after the warm-up; with the threshold fixed at glibc's default (environment
``MALLOC_MMAP_THRESHOLD_=131072``, the same as `fix_mmap_threshold`) 1.25 MB. ``MALLOC_ARENA_MAX=2``
alone did not help (+8.2 MB).

`fix_mmap_threshold` sets the threshold explicitly (``mallopt(M_MMAP_THRESHOLD, …)``), which also
turns the dynamic adjustment off (mallopt(3)). `host.cli.main` calls it for every command, unless
the user chose a threshold in the environment. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys

#: <malloc.h>
M_MMAP_THRESHOLD = -3
#: glibc's initial threshold, bytes: what `fix_mmap_threshold` keeps
MMAP_THRESHOLD = 128 * 1024
#: the environment variable through which a user sets the threshold themselves (mallopt(3))
ENV_VAR = "MALLOC_MMAP_THRESHOLD_"


def fix_mmap_threshold(threshold: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes (module docstring). Returns whether it was
    set: False off glibc, or when the user set ``MALLOC_MMAP_THRESHOLD_`` (theirs stands)."""
    if not sys.platform.startswith("linux") or ENV_VAR in os.environ:
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no libc.so.6)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, int(threshold)))
