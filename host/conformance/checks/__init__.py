"""The conformance checks: each holds the node under test to one clause of docs/protocol.md.

A check is a function of the `Session`; it returns a detail string (PASS), raises `CheckFailed`
(FAIL: the node violated the clause) or `Skip` (it could not run: no node, no evidence). Each is
registered with the clause it holds the node to, whether that clause is a MUST (a failure fails
the node) or a SHOULD (reported as "SHOULD not met", never a failure), its profile (``chip``: the
first chip to answer, directly or behind any gateway; ``gateway``: the first gateway node, §13),
what a failure means and how a vendor fixes it; `table()` renders that as docs/conformance.md (a
test keeps the file and the registry identical, another that every normative clause has a check).

Checks run in order and leave the node in a known state for the next; each that needs a state
gets there itself (`Session.ensure_idle`, `to_streaming`, `fresh_boot`), so ``--only`` may pick any.
Nothing passes on no evidence: a check that saw nothing to judge is a SKIP saying why.

One module per part of the spec; importing them in this order numbers the checks in run order:
`discovery` (§3, BOOT), `idle` (§4, §8), `streaming` (§5), `gateway` (§13), `wire` (§6, §7 over
everything the node sent), `imu` (§16, §17). `registry` holds `Check`, `CHECKS` and `table()`.
"""

from __future__ import annotations

from . import discovery, idle, streaming, gateway, wire, imu  # noqa: F401  (registers the checks, in run order)
from .discovery import theil_sen_period
from .registry import (CHECKS, INFORMATIVE, PROFILES, SHOULD_NOT_MET, Check, check, clauses_covered,
                       discovery_check, table)

__all__ = ["Check", "CHECKS", "INFORMATIVE", "SHOULD_NOT_MET", "PROFILES", "table", "clauses_covered",
           "discovery_check", "check", "theil_sen_period"]
