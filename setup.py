"""Only for the C extension: builds firmware_ref._capsheet_fw (the reference chip firmware) with cffi
at install time. Everything else is in pyproject.toml."""

from setuptools import setup

setup(cffi_modules=["firmware_ref/build_ffi.py:ffibuilder"])
