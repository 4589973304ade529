"""Running the checks: selection (``--only``), retries after port losses, results and summary.

Outcomes: PASS; FAIL (the chip violated the clause); SKIP (the check could not run: no chip, a
broadcast check without ``allow_broadcast``, the other transport's check); LOST (the port lost
frames during the check on every attempt: inconclusive, *not* a chip violation).

A check that fails while the port damaged frames (`Port.lossy`) is run again, up to ``attempts``
times; it is reported PASS if a later attempt passes (the detail says so), LOST if none does.
Transport errors (`host.transport.ports.TransportError`: the port went away) end the run: they propagate,
as does `RunAborted` (``node`` is another chip's).
"""

from __future__ import annotations

from dataclasses import dataclass

from host.transport.ports import TransportError

from .checks import CHECKS, PROFILES, SHOULD_NOT_MET, Check, discovery_check
from .session import CheckFailed, Port, PortLost, RunAborted, Session, Skip

__all__ = ["CheckResult", "select", "run_checks", "summary", "exit_code"]


@dataclass(frozen=True)
class CheckResult:
    number: int
    clause: str
    title: str
    outcome: str  #: PASS, FAIL, SKIP or LOST
    detail: str = ""
    attempts: int = 1

    def line(self) -> str:
        return f"{self.outcome:4}  {self.number:2d}  {self.clause:18} {self.title}" + \
            (f"  [{self.detail}]" if self.detail else "")


def select(only: list[str] | None, profile: str = "chip") -> list[Check]:
    """The checks of ``profile`` named by ``only`` (numbers, or clause prefixes like ``4.6`` / ``§5``),
    in run order.

    The profile's discovery check is always included. Raises ValueError naming any item that matches
    no check of the profile.
    """
    if profile not in PROFILES:
        raise ValueError(f"Invalid profile {profile!r} (known: {', '.join(PROFILES)})")
    first = discovery_check(profile)
    mine = [first] + [c for c in CHECKS if profile in c.profiles and c is not first]  # discovery runs first
    if not only:
        return mine
    chosen: set[int] = {discovery_check(profile).number}
    for o in only:
        o = o.strip()
        if not o:
            continue
        if o.isdigit():
            n = int(o)
            if not any(c.number == n for c in mine):
                raise ValueError(f"Invalid --only item {o!r}: there is no check {n} in the {profile} profile "
                                 f"(its checks: {', '.join(str(c.number) for c in mine)})")
            chosen.add(n)
            continue
        prefix = o.lstrip("§")
        hits = {c.number for c in mine for cl in c.clauses if cl == prefix or cl.startswith(prefix + ".")}
        if not hits:
            raise ValueError(f"Invalid --only item {o!r}: no check of the {profile} profile holds a node to "
                             f"clause §{prefix}")
        chosen |= hits
    return [c for c in mine if c.number in chosen]


def _run_one(c: Check, s: Session, attempts: int) -> CheckResult:
    port = s.port
    losses = []
    for attempt in range(1, attempts + 1):
        lost0 = port.lost
        try:
            detail = c.fn(s) or ""
            outcome = "PASS"
        except Skip as exc:
            return CheckResult(c.number, c.clause, c.title, "SKIP", str(exc), attempt)
        except (TransportError, RunAborted):
            raise
        except PortLost as exc:
            outcome, detail = "LOST", str(exc)
        except CheckFailed as exc:
            outcome, detail = "FAIL", str(exc)
        except Exception as exc:  # noqa: BLE001 - a broken device must not stop the battery
            outcome, detail = "FAIL", f"{type(exc).__name__}: {exc}"
        lost = port.lost - lost0
        if outcome != "PASS" and lost:
            chip = s.systematic_damage()
            if chip:  # the damage is the node's own encoding (§6.2), not the port: no retry, a FAIL
                return CheckResult(c.number, c.clause, c.title, "FAIL", f"{chip}; {detail}", attempt)
        if outcome == "PASS":
            if losses:
                detail += f" (passed on attempt {attempt}; the port lost {sum(losses)} frames before)"
            return CheckResult(c.number, c.clause, c.title, "PASS", detail, attempt)
        if outcome == "LOST" or (lost and port.lossy):
            losses.append(lost)
            if attempt < attempts:
                continue
            return CheckResult(c.number, c.clause, c.title, "LOST",
                               f"port lost frames ({sum(losses)} damaged in {attempt} attempts, "
                               f"{dict(port.damage)}): inconclusive, not a chip violation; last: {detail}", attempt)
        return CheckResult(c.number, c.clause, c.title, "FAIL", detail, attempt)
    raise AssertionError("unreachable")  # pragma: no cover


def run_checks(port: Port, *, timeout_s: float = 0.5, node: int | None = None, uid: int | None = None,
               slack_ms: float = 10.0, only: list[str] | None = None, allow_broadcast: bool = False,
               attempts: int = 3, out=None, profile: str = "chip") -> list[CheckResult]:
    """Run the selected checks of ``profile`` in order against the first node of that kind that
    answers (or ``uid``): a chip (the default), or a gateway node.

    Parameters
    ----------
    port : Port
        The port, over a host transport.
    timeout_s : float
        Seconds to wait for each answer (the other waits derive from it: session.py).
    node : int, optional
        Node id to assign for the run; default: the highest one no chip was heard from.
    uid : int, optional
        The chip under test; default: the first to answer the broadcast GET_INFO.
    slack_ms : float
        Host-side latency allowed on top of time limits (SYNC deadline, periods).
    only : list of str, optional
        `select`: check numbers or clause prefixes. ValueError for one that matches nothing.
    allow_broadcast : bool
        Run the checks that broadcast state-changing commands (they address every chip on the port).
    attempts : int
        Tries per check when the port lost frames.
    out : file-like, optional
        Each result's line is printed there as it completes.
    profile : {"chip", "gateway"}
        Which kind of node is held to the spec (docs/protocol.md §11).

    Returns
    -------
    list of CheckResult
        One per check run (the other transport's checks are left out). The chip is left in BOOT.
    """
    chosen = select(only, profile)
    s = Session(port, timeout_s=timeout_s, node=node, slack_ms=slack_ms, uid=uid, allow_broadcast=allow_broadcast,
                profile=profile)
    first = discovery_check(profile).number
    results = []
    for c in chosen:
        if c.transport and c.transport != port.kind:
            continue
        if c.number != first and c.needs_node and results and results[0].number == first \
                and results[0].outcome != "PASS":
            r = CheckResult(c.number, c.clause, c.title, "SKIP", f"no {profile} found (check {first})")
        elif c.broadcast and not allow_broadcast:
            r = CheckResult(c.number, c.clause, c.title, "SKIP",
                            "broadcast check: run with --allow-broadcast (it addresses every chip on the port)")
        else:
            r = _run_one(c, s, attempts)
        results.append(r)
        if out is not None:
            print(r.line(), file=out, flush=True)
    if s.cur is not None and s.info is not None:
        try:  # leave the chip under test unassigned, as a fresh one
            s.fresh_boot()
        except (CheckFailed, Skip):
            pass
    return results


def summary(results: list[CheckResult]) -> str:
    n = {k: sum(r.outcome == k for r in results) for k in ("PASS", "FAIL", "SKIP", "LOST")}
    lost = f", {n['LOST']} inconclusive (port lost frames)" if n["LOST"] else ""
    should = sum(r.outcome in ("PASS", "SKIP") and r.detail.startswith(SHOULD_NOT_MET) for r in results)
    should = f" ({should} with a SHOULD not met)" if should else ""
    return f"conformance: {n['PASS']} checks passed{should}, {n['FAIL']} failed, {n['SKIP']} skipped{lost}"


def exit_code(results: list[CheckResult]) -> int:
    """0 all passed (or skipped), 1 a check failed, 3 none failed but some were inconclusive."""
    if any(r.outcome == "FAIL" for r in results):
        return 1
    return 3 if any(r.outcome == "LOST" for r in results) else 0
