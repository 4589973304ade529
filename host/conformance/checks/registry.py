"""The registry of conformance checks: `Check`, the `check` decorator that numbers them in run order,
the clauses without a check (`INFORMATIVE`), and `table()`, which renders docs/conformance.md."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..session import Session


__all__ = ["Check", "CHECKS", "INFORMATIVE", "SHOULD_NOT_MET", "PROFILES", "table", "clauses_covered",
           "discovery_check"]

PROFILES = ("chip", "gateway")


@dataclass(frozen=True)
class Check:
    """One numbered check.

    Attributes
    ----------
    number : int
        1.. in run order (``--only 5``).
    clauses : tuple of str
        docs/protocol.md clause numbers it holds the node to, the first the one it is named by,
        e.g. ``("4.6", "12")``.
    title : str
        What is checked.
    meaning : str
        What a FAIL means about the node.
    fix : str
        How to fix it.
    fn : callable
        ``fn(session) -> str | None``.
    transport : str or None
        ``"serial"`` or ``"can"`` if it runs on that transport only.
    broadcast : bool
        It sends broadcast commands that change node state: runs only with ``--allow-broadcast``.
    level : str
        ``"MUST"`` (a failure fails the node), ``"SHOULD"`` (reported, never a failure) or
        ``"MUST; SHOULD reported"`` (the check holds a MUST and reports a SHOULD beside it).
    profiles : tuple of str
        The profiles it runs in (`PROFILES`).
    """

    number: int
    clauses: tuple[str, ...]
    title: str
    meaning: str
    fix: str
    fn: Callable[[Session], "str | None"]
    transport: str | None = None
    broadcast: bool = False
    level: str = "MUST"
    profiles: tuple[str, ...] = ("chip",)
    needs_node: bool = True  #: skipped when the discovery check found no node

    @property
    def clause(self) -> str:
        return "/".join(f"§{c}" for c in self.clauses)


CHECKS: list[Check] = []

#: detail prefix of a PASS whose SHOULD (not MUST) was not met
SHOULD_NOT_MET = "SHOULD not met:"

#: clauses of docs/protocol.md with no behaviour a node can be checked for from the wire, and why
INFORMATIVE: dict[str, str] = {
    "1": "overview; every requirement it mentions is restated, normatively, in a later clause",
    "1.1": "the lattice's link order and the sensor frame are the host's conventions: a chip stores the "
           "link index ASSIGN gives it (check 7) and reports its axes as mounted; its orientation needs a "
           "fixture (check 25 holds the magnitude, |a| = 1 g at rest)",
    "1.2": "definitions (node, segment, transparent bridge); what a gateway node must do is §13",
    "8.6": "FAULT follows a sensor failure, which cannot be caused from the wire; tests/vectors/chip.json "
           "holds every reference chip to it (the fault_* scenarios)",
    "8.7": "a receive buffer's size is not visible from the wire; check 21 sends a run longer than any frame",
    "9": "the golden vectors themselves; checks 39 and 40 hold every frame to the reference encoding",
    "10": "capacity figures derived from the frame sizes (`capsheet protocol capacity`), no node behaviour",
    "11": "this suite itself",
    "13.4": "the gateway's table, restated by §13.1 and held by checks 3, 6, 7, 14, 17, 19, 33 and 35",
    "14": "the timing table; each number is held by the check of the clause it names (8, 11, 24, 36, 37, 38)",
    "15": "the list of changes from 1.0",
    "16": "overview of the IMU chips; its clauses are held by checks 42-44 on a chip whose INFO has GYRO "
          "(skipped on an accelerometer-only chip, to which §16 does not apply)",
    "16.6": "where the new clauses are checked and counted: this suite and `capsheet protocol capacity`",
    "16.7": "the list of changes from 1.1",
    "17": "overview of the chip's gyroscope and magnetometer calibration; its clauses are held by check 45",
    "17.4": "where §17 is checked: this suite (check 45)",
    "17.5": "the list of changes from 1.2",
    "18": "the questions 1.4 answers: each amends the clause it names and is held by the check of that clause, "
          "a golden vector, a chip scenario of tests/vectors/chip.json or a gateway scenario, as it says",
}


def check(clauses: str, title: str, meaning: str, fix: str, *, transport: str | None = None,
          broadcast: bool = False, level: str = "MUST", profiles: tuple[str, ...] = ("chip",),
          needs_node: bool = True):
    def deco(fn):
        CHECKS.append(Check(len(CHECKS) + 1, tuple(c.strip().lstrip("§") for c in clauses.split(",")), title,
                            meaning, fix, fn, transport, broadcast, level, profiles, needs_node))
        return fn
    return deco


def clauses_covered(transport: str | None = None) -> set[str]:
    return {c for k in CHECKS if transport in (None, k.transport) or k.transport is None for c in k.clauses}


def should(s: Session, ok: bool, what: str, detail: str) -> str:
    """The detail of a check whose MUST passed, with its SHOULD reported."""
    return detail if ok else f"{SHOULD_NOT_MET} {what}; {detail}"



def table() -> str:
    """The checks as the markdown table of docs/conformance.md."""
    lines = ["| # | profile | clauses | level | check | a FAIL means | fix |", "|---|---|---|---|---|---|---|"]
    for c in CHECKS:
        only = f" *({c.transport} only)*" if c.transport else ""
        bc = " *(--allow-broadcast)*" if c.broadcast else ""
        cells = [str(c.number), ", ".join(c.profiles), c.clause, c.level, c.title + only + bc, c.meaning, c.fix]
        lines.append("| " + " | ".join(x.replace("|", "\\|") for x in cells) + " |")
    lines += ["", "Clauses without a check of their own, and why:", ""]
    lines += [f"- §{k}: {v}" for k, v in INFORMATIVE.items()]
    return "\n".join(lines) + "\n"


def discovery_check(profile: str) -> Check:
    """The check that finds the node under test: always run first in its profile."""
    name = "c_gateway_discover" if profile == "gateway" else "c_discover"  # checks.gateway, checks.discovery
    return next(c for c in CHECKS if c.fn.__name__ == name)
