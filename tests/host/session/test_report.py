"""`host.session.report.EventLog` alone, on a simulated clock: events stamped with the clock, bounded with
what goes counted, every kind counted, receive errors bounded and counted. (The run summary and
stats of a running host: tests/host/session/test_session.py, tests/host/test_long_run.py.)"""

from __future__ import annotations

import logging

from host.session.report import EVENTS_KEPT, RX_ERRORS_KEPT, EventLog, HostEvent, link_ranges


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_an_event_is_stamped_by_the_clock_and_kept_with_what_it_names():
    clock = Clock()
    log = EventLog(clock)
    log.report("silent", "link 3 silent", link=3, node=4, quiet=True)
    clock.t = 100.5
    log.report("recovered", "link 3 speaks again", link=3, quiet=True)
    assert log.events == [HostEvent(100.0, "silent", "link 3 silent", link=3, node=4),
                          HostEvent(100.5, "recovered", "link 3 speaks again", link=3)]
    assert log.event_counts == {"silent": 1, "recovered": 1} and log.events_cut == 0


def test_events_are_bounded_the_oldest_half_cut_and_counted_every_kind_counted():
    log = EventLog(Clock())
    n = 2 * EVENTS_KEPT + 7
    for k in range(n):
        log.report("stray" if k % 2 else "nack", f"event {k}", quiet=True)
    assert log.events_cut + len(log.events) == n and len(log.events) <= EVENTS_KEPT
    # full at EVENTS_KEPT + 1: half cut at the 10,001st, 15,001st and 20,001st event
    assert log.events_cut == 3 * (EVENTS_KEPT // 2) and len(log.events) == EVENTS_KEPT // 2 + 7
    assert log.events[-1].detail == f"event {n - 1}" and log.events[0].detail == f"event {log.events_cut}"
    assert log.event_counts == {"nack": EVENTS_KEPT + 4, "stray": EVENTS_KEPT + 3}


def test_warning_kinds_are_logged_as_warnings_others_as_info_quiet_ones_not_at_all(caplog):
    log = EventLog(Clock())
    with caplog.at_level(logging.INFO, logger="capsheet.host"):
        log.report("silent", "a", quiet=True)
        log.report("silent", "b")
        log.report("announce", "c")
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [(logging.WARNING, "silent: b"),
                                                                     (logging.INFO, "announce: c")]


def test_receive_errors_keep_the_newest_and_count_all():
    log = EventLog(Clock())
    for k in range(RX_ERRORS_KEPT + 5):
        log.rx_error(f"error {k}")
    assert log.rx_errors_total == RX_ERRORS_KEPT + 5
    assert log.rx_errors == [f"error {k}" for k in range(5, RX_ERRORS_KEPT + 5)]
    log.rx_errors.clear()  # a copy: the log keeps its own
    assert len(log.rx_errors) == RX_ERRORS_KEPT


def test_links_are_named_as_ranges():
    assert link_ranges([9, 0, 1, 2, 3, 7, 10]) == "0–3, 7, 9–10"
    assert link_ranges(range(0, 40, 2), limit=3) == "0, 2, 4 and 17 more (20 links in all)"
