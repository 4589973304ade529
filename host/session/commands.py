"""Command rounds: how the host sends to the chips and collects their answers.

A round sends every request, waits ``timeout_s`` for the ACKs (NACKs, CAL_DATA), resends what is
unanswered, ``retries`` times (``timeout_s`` grows by half each attempt), and names the chips that
never answered in one log line. The receive path hands every answer to `CommandRounds.answer`
(NACKs are counted and logged once per kind per round); a round takes them from an inbox.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter
from typing import Callable

from protocol.messages import Ack, GetInfo, Message, MsgType, Nack

from host.session.registry import ChipRecord
from host.transport.ports import TransportError

__all__ = ["CommandRounds", "ACK_TIMEOUT_S", "RETRIES", "attempt_wait_s"]

#: how long a command round's first sending waits for answers (`host.session.core.Host`'s default
#: ``timeout_s``)
ACK_TIMEOUT_S = 0.25
#: how many times a command round sends again what was not answered (`host.session.core.Host`'s
#: default ``retries``)
RETRIES = 4


def attempt_wait_s(timeout_s: float, attempt: int) -> float:
    """How long attempt ``attempt`` (0: the first sending) of a command round waits for answers:
    each half as long again as ``timeout_s`` as the one before it."""
    return timeout_s * (1 + 0.5 * attempt)

log = logging.getLogger("capsheet.host")


class CommandRounds:
    """Sending (`send`, `broadcast`) and command rounds (`round`) of one `host.session.core.Host`.

    Attributes
    ----------
    nack_counts : Counter
        (command, reason) -> NACKs.
    inbox_dropped : int
        Answers dropped because nobody took them (the inbox is bounded).
    muted_sends : int
        Frames not sent to a port that had not yet answered as the sheet (`host.session.recovery`).
    """

    def __init__(self, host) -> None:
        self.host = host
        self.nack_counts: Counter = Counter()
        self.inbox_dropped = 0
        self.muted_sends = 0
        self._inbox: queue.Queue = queue.Queue(maxsize=100_000)
        self._round_lock = threading.RLock()
        self._nack_logged: set = set()  # one log line per (command, reason) per round
        self._send_failing: set[int] = set()

    # -- sending ---------------------------------------------------------------------------
    def send(self, bus: int, msg: Message) -> None:
        """``msg`` to transport ``bus``; nothing but GET_INFO to a port that came back and has not
        proven yet that it leads to this sheet (counted in ``muted_sends``)."""
        recovery = self.host.recovery
        recovery.check_port(bus)
        if bus in recovery.unproven and not isinstance(msg, GetInfo):
            self.muted_sends += 1  # a port that came back drives nothing before it answers as the sheet
            return
        self.host.transports[bus].send(msg)

    def broadcast(self, msg: Message) -> None:
        """``msg`` on every bus; a bus that fails is logged once per failure spell, not once per SYNC."""
        for bus in range(len(self.host.transports)):
            try:
                self.send(bus, msg)
                self._send_failing.discard(bus)
            except TransportError as exc:
                if bus not in self._send_failing:
                    self._send_failing.add(bus)
                    log.warning("%s", exc)

    # -- answers ---------------------------------------------------------------------------
    def answer(self, bus: int, msg: Message) -> None:
        """An ACK, NACK or CAL_DATA from the receive path: NACKs counted (per chip, the newest
        `ChipRecord.MAX_NACKS` kept), then queued for the round that waits for it."""
        if isinstance(msg, Nack):
            host = self.host
            uid = host.registry.uid_at(bus, msg.node)
            try:
                name = MsgType(msg.command).name
            except ValueError:  # a command this host does not know (a newer peer's): its number
                name = str(msg.command)
            if uid is not None:
                nacks = host.registry.chips[uid].nacks
                nacks.append((name, msg.reason.name))
                if len(nacks) > ChipRecord.MAX_NACKS:
                    del nacks[0]
            key = (name, msg.reason.name)
            self.nack_counts[key] += 1
            first = key not in self._nack_logged
            self._nack_logged.add(key)
            host.report("nack", f"node {msg.node} refused {name}: {msg.reason.name}"
                        + (" (further NACKs of this kind in this round are counted, not logged)" if first else ""),
                        quiet=not first, node=msg.node, uid=uid)
        try:
            self._inbox.put_nowait((bus, msg))
        except queue.Full:
            self.inbox_dropped += 1

    def drop_answers(self) -> None:
        """Forget every answer not taken yet (stale: a previous round's, a previous session's)."""
        while True:
            try:
                self._inbox.get_nowait()
            except queue.Empty:
                break

    def _next_answer(self, timeout_s: float):
        """The next answer, waiting at most ``timeout_s``; raises queue.Empty."""
        host = self.host
        if not host.manual:
            return self._inbox.get(timeout=timeout_s)
        end = host.now() + timeout_s
        while True:
            try:
                return self._inbox.get_nowait()
            except queue.Empty:
                if host.now() >= end:
                    raise
                host.idle(min(host.tick_s, end - host.now()))

    # -- rounds ----------------------------------------------------------------------------
    def round(self, requests: dict, build: Callable[[object, int], list[tuple[int, Message]]],
              match: Callable[[int, Message], object | None], what: str) -> tuple[dict, list]:
        """Send every request, collect answers, resend the unanswered; ``retries`` times.

        ``requests``: key -> anything; ``build(key, attempt)`` -> [(bus, message), ...];
        ``match(bus, msg)`` -> key answered (by an ACK, NACK or CAL_DATA) or None.
        Returns ``(answers: key -> message, unanswered keys)``.
        """
        self.host.open()
        with self._round_lock:
            return self._round_locked(requests, build, match, what)

    def _round_locked(self, requests, build, match, what) -> tuple[dict, list]:
        host = self.host
        answers: dict = {}
        pending = set(requests)
        self._nack_logged = set()  # one log line per (command, reason) per round
        self.drop_answers()
        for attempt in range(host.retries + 1):
            if not pending:
                break
            send_failed = 0
            for key in list(pending):
                for bus, msg in build(key, attempt):
                    try:
                        self.send(bus, msg)
                    except TransportError as exc:
                        send_failed += 1
                        if send_failed == 1:
                            log.warning("%s: %s", what, exc)
            deadline = host.now() + attempt_wait_s(host.timeout_s, attempt)
            while pending:
                remaining = deadline - host.now()
                if remaining <= 0:
                    break
                try:
                    bus, msg = self._next_answer(remaining)
                except queue.Empty:
                    break
                key = match(bus, msg)
                if key is not None and key in pending:
                    answers[key] = msg
                    pending.discard(key)
        key_name = host.registry.key_name
        for key in pending:
            host.report("no_ack", f"{what}: no answer from {key_name(key)} after {host.retries + 1} "
                                  f"attempts", quiet=True)
        if pending:  # one line per round, not one per chip
            names = sorted(key_name(k) for k in pending)
            log.warning("%s: no answer from %d chip(s) after %d attempts: %s%s", what, len(pending),
                        host.retries + 1, ", ".join(names[:6]), " ..." if len(names) > 6 else "")
        return answers, sorted(pending, key=repr)

    def simple_round(self, make: Callable[[ChipRecord], Message], command: MsgType, what: str,
                     uids=None) -> list[ChipRecord]:
        """One message per assigned chip (of ``uids``), answered by an ACK or NACK of ``command``.
        Returns the chips that ACKed."""
        chips = self.host.registry.by_node(uids)

        def match(bus, msg):
            return (bus, msg.node) if isinstance(msg, (Ack, Nack)) and msg.command == command else None

        answers, _ = self.round(chips, lambda key, _a: [(key[0], make(chips[key]))], match, what)
        return [chips[k] for k, m in answers.items() if isinstance(m, Ack)]
