"""capsheet runs BLAS on one thread unless the user chose otherwise (host.runtime.one_blas_thread, which every command calls)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from host.cli import BLAS_THREAD_VARS

# numpy's OpenBLAS is loaded before main() runs (the CLI modules import numpy), scipy's after:
# both must end up limited. A real subcommand runs first.
PROBE = """
import json, sys
import numpy
from host.cli import main
rc = main(["protocol", "capacity"])
import scipy.linalg, scipy.sparse.linalg
from threadpoolctl import threadpool_info
print("\\n" + json.dumps({"rc": rc, "blas": [(i["prefix"], i["num_threads"]) for i in threadpool_info()
                                          if i["user_api"] == "blas"]}))
"""


def _run(env_extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARS}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_capsheet_limits_every_loaded_blas_to_one_thread():
    got = _run({})
    assert got["rc"] == 0
    assert got["blas"], "no BLAS library found loaded"
    assert {n for _, n in got["blas"]} == {1}, got["blas"]


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="a one-core machine runs BLAS on one thread anyway")
def test_a_thread_count_the_user_chose_is_kept():
    got = _run({"OPENBLAS_NUM_THREADS": "2"})
    assert {n for _, n in got["blas"]} == {2}, got["blas"]


def test_streaming_commands_shorten_the_interpreters_switch_interval_never_lengthen_it():
    """`short_gil_switch` (capsheet host, capsheet demo): a thread waiting for the interpreter lock
    gets it within 0.5 ms; an interval already shorter is kept; it returns the one it replaced."""
    import sys

    from host.cli import STREAMING_SWITCH_INTERVAL_S, short_gil_switch
    saved = sys.getswitchinterval()
    try:
        sys.setswitchinterval(0.005)
        assert short_gil_switch() == 0.005
        assert abs(sys.getswitchinterval() - STREAMING_SWITCH_INTERVAL_S) < 2e-6 and STREAMING_SWITCH_INTERVAL_S == 0.0005
        sys.setswitchinterval(0.0001)
        short_gil_switch()
        assert abs(sys.getswitchinterval() - 0.0001) < 2e-6  # kept (held in whole µs)
    finally:
        sys.setswitchinterval(saved)


# a command started in a process of its own: no numpy yet when main() runs (the parser of a command
# imports only its own subcommand); threadpoolctl is not needed then, the variables do it
FRESH = """
import json, sys
from host.cli import main
rc = main(["protocol", "capacity"])
before = "threadpoolctl" in sys.modules
import numpy, scipy.linalg
from threadpoolctl import threadpool_info
print("\\n" + json.dumps({"rc": rc, "threadpoolctl_at_start": before,
                          "blas": [(i["prefix"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]}))
"""


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="a one-core machine runs BLAS on one thread anyway")
def test_a_blas_loaded_after_a_commands_start_is_limited_too():
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARS}
    out = subprocess.run([sys.executable, "-c", FRESH], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["rc"] == 0 and got["threadpoolctl_at_start"] is False
    assert got["blas"] and {n for _, n in got["blas"]} == {1}, got["blas"]
