"""cffi build of the fused estimator's per-link kernel as ``host.analysis.motion._link_kernel``
(API mode), at install time through ``setup.py's`` ``cffi_modules``, or by hand::

    .venv/bin/python host/analysis/motion/_kernel/build_link_kernel.py

Optional at run time: without it (no compiler, or ``CAPSHEET_NO_KERNEL=1``) the fused estimator
runs its numpy code, which gives the same numbers to rounding
(tests/host/analysis/test_motion_kernel.py).
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


def _builder(absolute: bool = False) -> FFI:
    """The cffi builder; ``absolute``: the sources by absolute path (a build outside the project
    root, `__main__`), else relative to it (setuptools' ``cffi_modules``)."""
    srcs, inc = [HERE / "link_filter.c", HERE / "consider_filter.c"], HERE
    ffi = FFI()
    ffi.cdef(CDEF)
    ffi.set_source(
        "host.analysis.motion._link_kernel",
        '#include "link_filter.h"\n',
        sources=[str(src) if absolute else _B.rel_source(src) for src in srcs],
        include_dirs=[str(inc) if absolute else _B.rel_source(inc)],
        # no -ffast-math: the numbers must be the numpy fallback's (IEEE order of operations)
        extra_compile_args=(["-O3", "-fno-fast-math", "-ffp-contract=off"] if os.name != "nt"
                            else []),
    )
    return ffi


ffibuilder = _builder()

if __name__ == "__main__":
    print(*_shared().build_in_place(_builder(absolute=True), ROOT / "host" / "analysis" / "motion"))
