"""Load the compiled C firmware (``firmware_ref._capsheet_fw``) with a clear message if it is missing."""

from __future__ import annotations

try:
    from ._capsheet_fw import ffi, lib  # noqa: F401
except ImportError as exc:  # pragma: no cover - depends on the installation
    raise ImportError(
        "The C reference firmware extension (firmware_ref._capsheet_fw) is not built. It is built "
        "when capsheet is installed (`pip install -e .`, needs a C compiler such as gcc), or by hand "
        f"with `python firmware_ref/build_ffi.py`. ({exc})") from exc

__all__ = ["ffi", "lib"]
