"""Protocol conformance: hold one chip (real, virtual or a gateway with chips) to docs/protocol.md.

`host.conformance.checks` holds the numbered checks and `run_checks`; `capsheet conformance`
(`host/cli/conformance.py`) is the command line over them.
"""

from .checks import CHECKS, CanLink, CheckResult, Link, SerialLink, run_checks, summary

__all__ = ["CHECKS", "CheckResult", "Link", "SerialLink", "CanLink", "run_checks", "summary"]
