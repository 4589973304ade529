"""Protocol conformance: hold one chip (real, virtual, or behind a gateway) to docs/protocol.md.

Runs numbered checks, each holding the chip to clauses of the spec (docs/conformance.md is the table:
clause -> checks -> what a failure means -> how to fix it), through a host transport — a serial port
(pyserial: a USB adapter, a pty, ``socket://`` to an emulator) or a CAN interface (python-can) —
and reports PASS / FAIL / SKIP / LOST per check. The device under test may be anything that speaks
capsheet v1: the Python chip model, the C reference firmware (cffi or on QEMU), or hardware.

Modules: `session` (the port reader, event-driven waits, the chip under test), `checks` (the checks
and the clause table), `runner` (selection, retries, results), `simulated` (a run on a simulated
clock against an in-process chip model: `SimulatedPort` steps the device instead of waiting).

Safe on a full sheet: the chip under test is the first to answer a broadcast GET_INFO (or
``--uid``); the run assigns it a node id no chip was heard from; every command is addressed to it,
except SYNC (always broadcast: other *streaming* chips answer it and count the gaps) and the
broadcast checks, which run only with ``allow_broadcast``. The chip under test is left in BOOT.

Timing is measured on the host, so it includes the host's and the port's latency: the heartbeat
period (Theil-Sen over 9 heartbeats) within 5 % + ``slack_ms``/2, the re-announce period (Theil-Sen over
the boot announce and 3 re-announces) within 5 % + ``slack_ms``; the SYNC -> SAMPLE median over 2 ms + ``slack_ms`` (a SHOULD) is reported, not failed.
The chip under test must lie still during the run (the sample check expects |a| = 1 g).
"""

from .checks import CHECKS, INFORMATIVE, Check, table
from .runner import CheckResult, exit_code, run_checks, select, summary
from .session import AuditedCanTransport, Port, Session, SimulatedClock, SimulatedPort

__all__ = ["CHECKS", "INFORMATIVE", "Check", "table", "CheckResult", "run_checks", "select", "summary",
           "exit_code", "Port", "Session", "AuditedCanTransport", "SimulatedClock", "SimulatedPort"]
