"""cffi build of the estimator's compiled kernel as ``host.analysis._yaw_kernel`` (API mode).

Built at install time through ``setup.py``'s ``cffi_modules`` (``pip install -e .``), or by hand::

    .venv/bin/python host/analysis/_kernel/build.py     # writes host/analysis/_yaw_kernel*.so

Optional at run time: without it (no compiler, not built, or ``CAPSHEET_NO_KERNEL=1``) the
estimator runs its numpy code, which gives the same numbers (tests/host/analysis/
test_estimator_kernel.py compares them).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]

def cdef_from_header(path: Path) -> str:
    """The header's declarations as cffi's ``cdef`` takes them (no comments, no preprocessor
    lines): one source for the C code and its Python binding."""
    text = re.sub(r"/\*.*?\*/", "", path.read_text(encoding="utf-8"), flags=re.S)
    return "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#"))


CDEF = cdef_from_header(HERE / "yaw_eval.h")


def rel_source(path: Path) -> str:
    # setuptools wants sources relative to the project root (the cwd of a build); by hand
    # (``__main__``) they are absolute, as cffi compiles in a directory of its own
    if __name__ == "__main__":
        return str(path)
    try:
        return os.path.relpath(path, os.getcwd())
    except ValueError:  # another drive (Windows)
        return str(path)


ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "host.analysis._yaw_kernel",
    '#include "yaw_eval.h"\n',
    sources=[rel_source(HERE / "yaw_eval.c"), rel_source(HERE / "heights.c"),
             rel_source(HERE / "ldl_factor.c")],
    include_dirs=[rel_source(HERE)],
    # no -ffast-math: the numbers must be the numpy fallback's (IEEE order of operations)
    extra_compile_args=["-O3", "-fno-fast-math", "-ffp-contract=off"] if os.name != "nt" else [],
)

def build_in_place(builder: FFI, where: Path) -> list[Path]:
    """Compile ``builder`` by hand and put the module in ``where``, over every build of it already
    there (pip's is .abi3.so: one left older would shadow or be shadowed by this one). Built in a
    scratch directory, not the project root: there cffi's distutils step would read pyproject.toml
    with the venv's own setuptools (Python 3.11's 65.x rejects its SPDX licence)."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        built = Path(builder.compile(tmpdir=tmp, verbose=False))
        stem = built.name.split(".")[0]
        dests = sorted(where.glob(stem + ".*so")) or [where / built.name]
        for dest in dests:  # a new file renamed over it: a process running the old one keeps it
            shutil.copy(built, dest.with_name(dest.name + ".new"))
            os.replace(dest.with_name(dest.name + ".new"), dest)
    return dests


if __name__ == "__main__":
    print(*build_in_place(ffibuilder, ROOT / "host" / "analysis"))
