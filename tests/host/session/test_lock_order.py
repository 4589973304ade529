"""The host's locks are always taken in one order, so no two threads can wait on each other.

A receive thread holds the feed's lock across one read (`SnapshotFeed.one_read`) and, inside it,
hands control frames to the chip registry, which takes the chip records' lock: feed, then registry.
Anything that held the registry's lock and then asked the feed for its lock would deadlock against
it. It did: `BringUp.read_calibration` applied the chips' calibration to the feed with the registry
locked, and a 64x64 host (8,064 chips, STATUS frames arriving during CAL_READ) hung for good in
bring-up (`benchmarks/bench_live.py --only 64x64-packed-5gw-record`, main thread in
`SnapshotFeed.set_calibration`, a receive thread in `ChipRegistry.uid_at`).

These tests replace the host's locks with ones that record, per thread, which lock was taken while
which was held, run the whole life of a host on the simulated clock (bring-up with calibration,
streaming with STATUS frames and a recovery, stop), and require the graph of those edges to have no
cycle: in one thread on the simulated clock (nothing can hang, the order is what is checked) and
with the host's threads over a pty.
"""

from __future__ import annotations

import threading

import pytest

from tests.host.test_back2back import Rig


class TracedLock:
    """An RLock that records, for each acquisition, the other traced locks its thread held."""

    _held = threading.local()

    def __init__(self, name: str, inner, edges: set) -> None:
        self.name, self._inner, self._edges = name, inner, edges

    def _stack(self) -> list:
        if not hasattr(self._held, "stack"):
            self._held.stack = []
        return self._held.stack

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        stack = self._stack()
        for other in stack:
            if other != self.name:
                self._edges.add((other, self.name))
        ok = self._inner.acquire(blocking, timeout)
        if ok:
            stack.append(self.name)
        return ok

    def release(self) -> None:
        stack = self._stack()
        if self.name in stack:  # (not when taken through the old reference before the swap)
            del stack[len(stack) - 1 - stack[::-1].index(self.name)]
        self._inner.release()

    __enter__ = acquire

    def __exit__(self, *exc) -> None:
        self.release()


def _replace_everywhere(root, old, new, seen=None) -> int:
    """Every attribute of the host's parts that is ``old`` becomes ``new``; returns how many."""
    seen = set() if seen is None else seen
    if id(root) in seen or not hasattr(root, "__dict__"):
        return 0
    seen.add(id(root))
    n = 0
    for key, value in list(vars(root).items()):
        if value is old:
            setattr(root, key, new)
            n += 1
        elif type(value).__module__.startswith("host."):
            n += _replace_everywhere(value, old, new, seen)
    return n


def _trace(host) -> set:
    edges: set = set()
    locks = {"registry": host._lock, "feed": host.feed._lock, "sync-step": host.sync_driver.step_lock}
    for name, lock in locks.items():
        assert _replace_everywhere(host, lock, TracedLock(name, lock, edges)) >= 1, name
    return edges


def _cycles(edges: set) -> list:
    """The pairs of locks taken in both orders (a cycle of two; longer ones are checked too)."""
    graph: dict = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)

    def reaches(a, b, seen=()):
        return any(n == b or (n not in seen and reaches(n, b, seen + (n,))) for n in graph.get(a, ()))

    return sorted((a, b) for a, b in edges if reaches(b, a))


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_a_host_takes_its_locks_in_one_order_through_bring_up_streaming_recovery_and_stop(kind):
    # a bus outage mid-stream: the chips go silent, the host recovers them (ASSIGN, CAL_READ, START);
    # memory: one thread on the simulated clock; pty: the receive, SYNC and recovery threads
    rig = Rig(kind, lattice="4x4", rate_hz=100.0, watchdog_s=0.15,
              faults="outage_at_s=0.7,outage_s=0.3,seed=11")
    try:
        edges = _trace(rig.host)
        rig.host.bring_up(0.3)  # discover, ASSIGN (the node map to the feed), CAL_READ (calibration to it)
        assert rig.host.calibration_reads >= 1
        snaps = rig.stream(1.6)
    finally:
        rig.close()
    assert snaps
    assert any(e.kind == "recovered" for e in rig.host.events)
    # the receive path's order is there (ANNOUNCE/STATUS handled inside one read) ...
    assert ("feed", "registry") in edges
    # ... and nothing takes them the other way round
    assert _cycles(edges) == [], sorted(edges)


def test_the_check_sees_a_lock_taken_the_other_way_round():
    """The tracer on its own: a cycle made on purpose is found (so an empty result means something)."""
    edges: set = set()
    a = TracedLock("a", threading.RLock(), edges)
    b = TracedLock("b", threading.RLock(), edges)
    with a:
        with b:
            pass
    assert _cycles(edges) == []
    with b:
        with a:
            pass
    assert _cycles(edges) == [("a", "b"), ("b", "a")]
