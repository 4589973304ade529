"""Where the test run's default Zenoh sessions meet: one loopback port per pytest-xdist worker.

capsheet's default sessions (no endpoint, no config file: host/publish/zenoh_session.py) meet at
one fixed loopback endpoint, ``tcp/127.0.0.1:7447``. Every worker of a run starting its hosts,
workers and subscribers there made them one Zenoh network: a worker's estimate checker heard the
other worker's sheets, and when the process holding the port ended, the sessions of both workers
waited for another to take it. Each worker (and a run without workers) therefore sets
``ZENOH_CONFIG_OVERRIDE`` (rmw_zenoh's variable, which capsheet applies over every config, as
docs/distribution.md says) to listen at and connect to a port of its own, in `install`, before any
test runs: every session the worker opens in its own process, and every process it starts (they
inherit the environment), meets there, and no session of another worker hears them.

The tests of a session given its own endpoint or config file (a router's locator, a TLS config)
take the variable out (`without_meeting`): it is applied last, so it would replace their endpoints.
The tests of the default endpoint itself (tests/host/publish/test_zenoh_session.py) take out every
``ZENOH*`` variable, as before, and meet at 7447.
"""

from __future__ import annotations

import os
import socket
import zlib

VAR = "ZENOH_CONFIG_OVERRIDE"
#: the ports the workers' meeting points are taken from: below Linux's ephemeral range (32768-60999,
#: /proc/sys/net/ipv4/ip_local_port_range), so no socket bound to port 0 (every Zenoh session's own
#: listener) is handed one of them while its worker has no session open
LOW, HIGH = 20000, 32000


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def meeting_port(environ=None) -> int:
    """This worker's port: one of `LOW`..`HIGH` chosen by the run (pytest-xdist's
    ``PYTEST_XDIST_TESTRUNUID``, else this process's id) and the worker's number (``gwN``), so two
    workers of a run never take the same one; the next of the worker's own if that one is taken."""
    env = os.environ if environ is None else environ
    worker = env.get("PYTEST_XDIST_WORKER", "")
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    stride = max(64, int(env.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1))
    run = env.get("PYTEST_XDIST_TESTRUNUID") or str(os.getpid())
    slots = (HIGH - LOW) // stride
    first = zlib.crc32(run.encode()) % slots
    for k in range(slots):
        port = LOW + ((first + k) % slots) * stride + index
        if _free(port):
            return port
    raise RuntimeError(f"no free loopback port for the Zenoh sessions of worker {worker or 'main'}")


def override(port: int) -> str:
    """The `VAR` value: listen at ``port`` (and at a port of the session's own, as the default does)
    and connect to it, the default's retries kept (host/publish/zenoh_session.py)."""
    here = f"tcp/127.0.0.1:{port}"
    return (f'listen/endpoints=["tcp/127.0.0.1:0","{here}#exit_on_failure=false"];'
            f'connect/endpoints=["{here}"]')


def install() -> str:
    """Set `VAR` in this process's environment to this worker's meeting point; returns it."""
    value = os.environ[VAR] = override(meeting_port())
    return value


def without_meeting(env=None) -> dict:
    """``env`` (default: this process's environment) without `VAR`, for a process whose session is
    given an endpoint or a config file of its own."""
    return {k: v for k, v in (os.environ if env is None else env).items() if k != VAR}
