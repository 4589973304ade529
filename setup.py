"""Only for the C extensions, built with cffi at install time: firmware_ref._capsheet_fw (the
reference chip firmware), host.analysis._yaw_kernel (the estimator's compiled kernel; the
estimator falls back to numpy without it) and host.analysis.tactile._response_kernel (the
tactile contact model's response; numpy without it), host.analysis.motion._link_kernel
(the fused estimator's per-link filter steps; numpy without it), protocol._stream_kernel (the
serial stream decoder's scan; numpy and Python without it). Everything else is in
pyproject.toml."""

from setuptools import setup

setup(cffi_modules=["firmware_ref/build_ffi.py:ffibuilder",
                    "firmware_ref/build_ffi.py:ffibuilder_mutants",
                    "host/analysis/_kernel/build.py:ffibuilder",
                    "host/analysis/tactile/_kernel/build_response.py:ffibuilder",
                    "host/analysis/motion/_kernel/build_link_kernel.py:ffibuilder",
                    "protocol/_kernel/build_stream.py:ffibuilder"])
