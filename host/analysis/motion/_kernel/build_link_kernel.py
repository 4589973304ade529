"""cffi build of the fused estimator's per-link kernel as ``host.analysis.motion._link_kernel``
(API mode), at install time through ``setup.py's`` ``cffi_modules``, or by hand::

    .venv/bin/python host/analysis/motion/_kernel/build_link_kernel.py

Optional at run time: without it (no compiler, or ``CAPSHEET_NO_KERNEL=1``) the fused estimator
runs its numpy code, which gives the same numbers (tests/host/analysis/test_motion_kernel.py).
"""

import os
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[3]

def _shared():
    """The estimator kernel's build script, for its public helpers (`cdef_from_header`,
    `rel_source`), loaded by path: at install time this file runs outside the package."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_capsheet_yaw_build",
                                                  HERE.parents[1] / "_kernel" / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_B = _shared()
CDEF = _B.cdef_from_header(HERE / "link_filter.h")


ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "host.analysis.motion._link_kernel",
    '#include "link_filter.h"\n',
    sources=[_B.rel_source(HERE / "link_filter.c")],
    include_dirs=[_B.rel_source(HERE)],
    # no -ffast-math: the numbers must be the numpy fallback's (IEEE order of operations)
    extra_compile_args=["-O3", "-fno-fast-math", "-ffp-contract=off"] if os.name != "nt" else [],
)

if __name__ == "__main__":
    os.chdir(ROOT)
    ffibuilder.compile(tmpdir=str(ROOT), verbose=False)
