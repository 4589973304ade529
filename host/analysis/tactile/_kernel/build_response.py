"""cffi build of the tactile contact model's response kernel as
``host.analysis.tactile._response_kernel`` (API mode).

Built at install time through ``setup.py``'s ``cffi_modules`` (``pip install -e .``), or by hand::

    .venv/bin/python host/analysis/tactile/_kernel/build_response.py   # host/analysis/tactile/_response_kernel*.so

Named ``build_response.py``, not ``build.py``: ``pytest --doctest-modules`` imports a file outside a
package by its basename, and host/analysis/_kernel/build.py has that one.

Optional at run time: without it (no compiler, not built, or ``CAPSHEET_NO_KERNEL=1``)
`host.analysis.tactile.response` runs its numpy code, which gives the same numbers to the
Bessel approximations' 3e-7 (tests/host/analysis/test_tactile_response.py compares them).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[3]


def _cdef_from_header(path: Path) -> str:
    """The header's declarations as cffi's ``cdef`` takes them (one source for both)."""
    text = re.sub(r"/\*.*?\*/", "", path.read_text(encoding="utf-8"), flags=re.S)
    return "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#"))


def _rel(path: Path) -> str:
    # setuptools wants sources relative to the project root (the cwd of a build).
    try:
        return os.path.relpath(path, os.getcwd())
    except ValueError:  # another drive (Windows)
        return str(path)


ffibuilder = FFI()
ffibuilder.cdef(_cdef_from_header(HERE / "response.h"))
ffibuilder.set_source(
    "host.analysis.tactile._response_kernel",
    '#include "response.h"\n',
    sources=[_rel(HERE / "response.c")],
    include_dirs=[_rel(HERE)],
    extra_compile_args=(["-O2", "-std=c99", "-D_DEFAULT_SOURCE", "-Wall", "-Wextra",
                         "-Wconversion"] if os.name != "nt" else []),
)

if __name__ == "__main__":
    os.chdir(ROOT)
    ffibuilder.compile(tmpdir=str(ROOT), verbose=False)
