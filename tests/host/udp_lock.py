"""The machine-wide lock of the udp_multicast tests: python-can's udp_multicast buses share one UDP
port, and on Linux a plain python-can bus on it hears every group (capsheet's own buses are isolated
to their group, host/transport/udp_multicast.py; the tests' injector buses and an older checkout's suite on
this machine are not), and most tests use the default group: two at once could hear each other's
RESET and SYNC. One at a time (a file lock)."""

from __future__ import annotations

import contextlib
import fcntl
import os


@contextlib.contextmanager
def udp_multicast_lock():
    with open(os.path.join("/tmp", "capsheet-udp-multicast-tests.lock"), "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
