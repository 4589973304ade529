"""cffi build of the stream decoder's compiled scan as ``protocol._stream_kernel`` (API mode).

Built at install time through ``setup.py``'s ``cffi_modules`` (``pip install -e .``), or by hand::

    .venv/bin/python protocol/_kernel/build_stream.py     # writes protocol/_stream_kernel*.so

Optional at run time: without it (no compiler, not built, or ``CAPSHEET_NO_KERNEL=1``)
`protocol.framing.StreamDecoder` runs its numpy and per-frame Python code, which gives the same
events (tests/protocol/test_stream_kernel.py compares them).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


def cdef_from_header(path: Path) -> str:
    """The header's declarations as cffi's ``cdef`` takes them (no comments, no preprocessor lines)."""
    text = re.sub(r"/\*.*?\*/", "", path.read_text(encoding="utf-8"), flags=re.S)
    return "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#"))


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
ffibuilder.cdef(cdef_from_header(HERE / "stream.h"))
ffibuilder.set_source(
    "protocol._stream_kernel",
    '#include "stream.h"\n',
    sources=[rel_source(HERE / "stream.c")],
    include_dirs=[rel_source(HERE)],
    extra_compile_args=["-O2", "-std=c99", "-Wall", "-Wextra"] if os.name != "nt" else [],
)

if __name__ == "__main__":
    import shutil
    import tempfile

    # built in a scratch directory, not the project root: there cffi's distutils step would read
    # pyproject.toml with the venv's own setuptools (Python 3.11's 65.x rejects its SPDX licence)
    with tempfile.TemporaryDirectory() as tmp:
        built = Path(ffibuilder.compile(tmpdir=tmp, verbose=False))
        where = ROOT / "protocol"
        # over every build of it already there (pip's is .abi3.so): one left older would shadow
        # or be shadowed by this one
        stem = built.name.split(".")[0]
        dests = sorted(where.glob(stem + ".*so")) or [where / built.name]
        for dest in dests:  # a new file renamed over it: a process running the old one keeps it
            shutil.copy(built, dest.with_name(dest.name + ".new"))
            os.replace(dest.with_name(dest.name + ".new"), dest)
    print(*dests)
