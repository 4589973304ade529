"""The conformance checks: each holds the chip under test to one or more clauses of docs/protocol.md.

A check is a function of the `Session`; it returns a detail string (PASS), raises `CheckFailed`
(FAIL: the chip violated the clause) or `Skip`. Each is registered with its clauses, what a failure
means and how a chip vendor fixes it; `table()` renders that as docs/conformance.md (a test keeps
the file and the registry identical, another that every normative clause has a check).

Checks run in order and leave the chip in a known state for the next; each that needs a state
gets there itself (`Session.ensure_idle`, `to_streaming`, `fresh_boot`), so ``--only`` may pick any.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Callable

from cobs import cobs

from protocol.can import decode_can
from protocol.crc import crc16_ccitt_false
from protocol.framing import HEADER, DecodeError, decode_frame, encode
from protocol.messages import (NODE_PROVISIONAL_MAX, NODE_PROVISIONAL_MIN, PROTOCOL_VERSION, Ack, Announce,
                               Assign, CalData, CalRead, CalWrite, Capability, ChipState, Config, GetInfo, Info,
                               Message, MsgType, Nack, NackReason, Reset, Sample, Start, Status, StatusFlag, Stop, Sync,
                               provisional_node)
from protocol.constants import SampleStatus
from protocol.state import ANNOUNCE_PERIOD_S, SYNC_REPLY_DEADLINE_S

from .session import HEARTBEAT_MS, acked, AuditedCanTransport, CheckFailed, PortLost, RunAborted, Session, Skip, require

__all__ = ["Check", "CHECKS", "INFORMATIVE", "SHOULD_NOT_MET", "table", "clauses_covered"]


@dataclass(frozen=True)
class Check:
    """One numbered check.

    Attributes
    ----------
    number : int
        1.. in run order (``--only 5``).
    clauses : tuple of str
        docs/protocol.md clause numbers it holds the chip to, e.g. ``("4.6", "12")``.
    title : str
        What is checked.
    meaning : str
        What a FAIL means about the chip.
    fix : str
        How to fix it in a chip.
    fn : callable
        ``fn(session) -> str | None``.
    transport : str or None
        ``"serial"`` or ``"can"`` if it runs on that transport only.
    broadcast : bool
        It sends broadcast commands that change chip state: runs only with ``--allow-broadcast``.
    """

    number: int
    clauses: tuple[str, ...]
    title: str
    meaning: str
    fix: str
    fn: Callable[[Session], "str | None"]
    transport: str | None = None
    broadcast: bool = False

    @property
    def clause(self) -> str:
        return "/".join(f"§{c}" for c in self.clauses)


CHECKS: list[Check] = []

#: detail prefix of a PASS whose SHOULD (not MUST) was not met
SHOULD_NOT_MET = "SHOULD not met:"

#: clauses of docs/protocol.md with no behaviour a chip can be checked for on its own, and why
INFORMATIVE: dict[str, str] = {
    "1": "overview; every requirement it mentions is restated, normatively, in a later clause",
    "1.1": "the lattice's link order and the sensor frame are the host's conventions: a chip stores the "
           "link index ASSIGN gives it (check 7) and reports its axes as mounted; its orientation needs a "
           "fixture (check 23 holds the magnitude, |a| = 1 g at rest)",
    "10": "capacity figures derived from the frame sizes (`capsheet protocol capacity`), no chip behaviour",
    "11": "this suite itself",
}


def check(clauses: str, title: str, meaning: str, fix: str, *, transport: str | None = None,
          broadcast: bool = False):
    def deco(fn):
        CHECKS.append(Check(len(CHECKS) + 1, tuple(c.strip().lstrip("§") for c in clauses.split(",")), title,
                            meaning, fix, fn, transport, broadcast))
        return fn
    return deco


def clauses_covered(transport: str | None = None) -> set[str]:
    return {c for k in CHECKS if transport in (None, k.transport) or k.transport is None for c in k.clauses}


# ---------------------------------------------------------------------------------------------
# Discovery, identity, BOOT
# ---------------------------------------------------------------------------------------------

@check("4.13, 4.1", "GET_INFO (broadcast) is answered with ANNOUNCE then INFO",
       "the chip cannot be discovered: a host never finds it",
       "answer GET_INFO addressed to node 0 or to the chip, in every state, with ANNOUNCE then INFO "
       "(two frames, in that order, from the current node id)")
def c_discover(s: Session):
    s.drain()
    s.port.send(GetInfo(0))
    window = max(1.0, 2 * s.timeout_s)  # every chip on the port answers; note every node id heard
    got = s.collect(window, lambda ms: any(isinstance(m, Info) for m in ms) and
                    any(isinstance(m, Announce) for m in ms))
    anns = [m for _, m in got if isinstance(m, Announce)]
    if s.uid is None:
        require(bool(anns), "no ANNOUNCE in answer to a broadcast GET_INFO"
                + (f" ({s.port.lost} damaged frames arrived: see §6.2)" if s.port.lost else ""))
    else:
        require(bool(anns), f"no ANNOUNCE from uid 0x{s.uid:016X} in answer to a broadcast GET_INFO")
    ann = anns[0]
    s.uid, s.cur = ann.uid, ann.node
    infos = [m for _, m in got if isinstance(m, Info) and m.node == ann.node]
    if not infos:
        infos = [m for _, m in s.collect(s.answer_s, lambda ms: any(isinstance(m, Info) for m in ms))
                 if isinstance(m, Info)]
    require(bool(infos), f"ANNOUNCE from node 0x{ann.node:04X} not followed by INFO")
    s.info = s.first_info = infos[0]
    s.collect(min(0.3, s.timeout_s))  # the other chips' answers: their node ids are in use
    if s.node is None:
        s.node = s.pick_node()
    elif s.node in s.nodes_seen and s.node != s.cur:
        raise RunAborted(f"--node 0x{s.node:04X} is in use by another chip on the port; omit --node to pick "
                         f"a free one")
    return (f"uid 0x{s.uid:016X}, node 0x{s.cur:04X}, state {s.info.state.name}; {len(s.nodes_seen)} node(s) "
            f"heard; the run uses node 0x{s.node:04X}")


@check("4.2", "INFO: protocol version 1, 12-bit ADC, reserved capability bits 0",
       "the host cannot trust the chip's self-description (version, ADC, capabilities)",
       "send protocol_version 1 and adc_bits 12; send capability bits 6..15 as 0")
def c_info(s: Session):
    s.need_chip()
    i = s.info
    require(i.protocol_version == PROTOCOL_VERSION, f"protocol_version {i.protocol_version}")
    require(i.adc_bits == 12, f"adc_bits {i.adc_bits}")
    require(int(i.capabilities) & ~0x3F == 0, f"reserved capability bits set: 0x{int(i.capabilities):04X}")
    return f"firmware {i.fw_major}.{i.fw_minor}.{i.fw_patch}, capabilities {Capability(int(i.capabilities) & 0x3F)!r}"


@check("4.14, 3.1", "RESET: ACK from the current node, then ANNOUNCE + INFO in BOOT, same uid",
       "a host cannot bring the chip back to a known state (and its uid is not stable)",
       "on RESET: ACK from the current node id, forget assignment and configuration, enter BOOT, send "
       "ANNOUNCE (the same factory uid) then INFO (state 0)")
def c_reset(s: Session):
    s.assign_without_reset()  # an assigned chip does not re-announce: only the RESET can cause the ANNOUNCE
    before = s.cur
    ans = s.request(Reset(s.cur), 3, keep=(Announce, Info))
    require(len(ans) == 3, f"expected ACK, ANNOUNCE, INFO; got {ans}")
    require(acked(ans[:1], before, MsgType.RESET), f"first answer {ans[0]}")
    require(isinstance(ans[1], Announce) and ans[1].uid == s.uid, f"second answer {ans[1]} (uid 0x{s.uid:016X})")
    require(isinstance(ans[2], Info) and ans[2].state == ChipState.BOOT and ans[2].node == ans[1].node,
            f"third answer {ans[2]}")
    s.cur = ans[1].node


@check("3.2", "an unassigned chip speaks from a provisional node id (0x8000..0xFFFE)",
       "an unassigned chip collides with assigned chips' node ids",
       "in BOOT, send from provisional_node(uid, salt) (§3.2), never from an assigned id")
def c_provisional(s: Session):
    s.fresh_boot()
    require(NODE_PROVISIONAL_MIN <= s.cur <= NODE_PROVISIONAL_MAX, f"node 0x{s.cur:04X}")
    rec = provisional_node(s.uid, 0)
    return "the recommended provisional_node(uid, 0)" if s.cur == rec else \
        f"0x{s.cur:04X} (not the recommended 0x{rec:04X}; allowed)"


@check("8", "a command not allowed in BOOT is refused: NACK BAD_STATE",
       "a host cannot tell that the chip ignored a command (START before ASSIGN)",
       "for a (state, command) pair not in the §8 table, addressed to the chip: NACK reason 4 BAD_STATE")
def c_bad_state_boot(s: Session):
    s.fresh_boot()
    ans = s.request(Start(s.cur))
    require(ans == [Nack(s.cur, MsgType.START, NackReason.BAD_STATE)], f"START in BOOT answered {ans}")


@check("4.10", "ASSIGN whose uid_low is another chip's is ignored silently",
       "two chips sharing a provisional id would both take the assignment",
       "compare uid_low with the low 32 bits of the uid; on a mismatch send nothing and change nothing")
def c_assign_wrong_uid(s: Session):
    s.fresh_boot()
    other = (s.uid ^ 0x5A5A5A5A) & 0xFFFFFFFF
    ans = s.silent(Assign(s.cur, new_node=s.node, link=0, uid_low=other))
    require(ans == [], f"answered {ans}")
    ans = s.request_info(s.cur)
    require(len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.BOOT,
            f"after a foreign ASSIGN, GET_INFO to the provisional id answered {ans}")


@check("4.10, 3.2", "ASSIGN: ACK from the new node id; the chip is IDLE there",
       "the chip cannot be assigned, or answers from the wrong node id",
       "on ASSIGN (addressed, uid_low matching): take new_node and link, ACK from new_node, enter IDLE")
def c_assign(s: Session):
    s.fresh_boot()
    ans = s.request(Assign(s.cur, new_node=s.node, link=3, uid_low=s.uid & 0xFFFFFFFF))
    require(acked(ans, s.node, MsgType.ASSIGN), f"answered {ans}")
    s.cur = s.node
    ans = s.request_info(s.node)
    require(len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.IDLE, f"GET_INFO: {ans}")


@check("3.2, 8", "an unassigned chip repeats ANNOUNCE + INFO every 1 s",
       "a host that starts after the chip never hears it (or is flooded)",
       "in BOOT, resend ANNOUNCE then INFO every 1 s (next deadline = max(previous + 1 s, now)) from a "
       "free-running time base")
def c_reannounce(s: Session):
    s.fresh_boot()
    t_boot = s.boot_t
    got = s.collect(ANNOUNCE_PERIOD_S * 2.6, lambda ms: sum(isinstance(m, Announce) for m in ms) >= 2
                    and isinstance(ms[-1], Info))
    times = [t_boot] + [t for t, m in got if isinstance(m, Announce)]
    require(len(times) >= 3, f"{len(times) - 1} re-ANNOUNCE within {ANNOUNCE_PERIOD_S * 2.6:.1f} s of a RESET")
    periods = [b - a for a, b in zip(times, times[1:])]
    mean = (times[-1] - times[0]) / (len(times) - 1)  # one late arrival lengthens one period, shortens the next
    tol = 0.05 * ANNOUNCE_PERIOD_S + s.slack_ms / 1000
    require(abs(mean - ANNOUNCE_PERIOD_S) <= tol, f"re-announce period {mean:.3f} s (1 s ± {tol * 1000:.0f} ms; "
                                                  f"periods {', '.join(f'{p:.3f}' for p in periods)} s)")
    ms = [m for _, m in got]
    pairs = [(a, b) for a, b in zip(ms, ms[1:]) if isinstance(a, Announce)]
    require(all(isinstance(b, Info) and b.node == a.node for a, b in pairs), f"re-ANNOUNCE not followed by INFO: {ms}")
    return f"periods {', '.join(f'{p:.3f}' for p in periods)} s"


# ---------------------------------------------------------------------------------------------
# IDLE: configuration, NACKs, calibration, heartbeat
# ---------------------------------------------------------------------------------------------

@check("4.11", "CONFIG (valid) is acknowledged",
       "the chip cannot be configured", "ACK a CONFIG whose fields are in range, in IDLE and FAULT")
def c_config(s: Session):
    s.ensure_idle()
    ans = s.request(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=HEARTBEAT_MS))
    require(acked(ans, s.node, MsgType.CONFIG), f"answered {ans}")


@check("4.4, 8.1", f"STATUS heartbeat every heartbeat_ms ({HEARTBEAT_MS} ms ± 5 % + slack/2), IDLE, CONFIGURED",
       "the host's liveness monitoring misjudges the chip (its clock or scheduler is off)",
       "send STATUS every heartbeat_ms from a free-running time base (a hardware counter, not a count of "
       "timer interrupts); next deadline = max(previous + period, now); set CONFIGURED after CONFIG")
def c_heartbeat(s: Session):
    s.ensure_idle()
    s.drain()
    n = 9
    st = s.statuses(n, timeout_s=n * HEARTBEAT_MS / 1000 * 1.5 + s.timeout_s)
    require(len(st) >= 3, f"{len(st)} STATUS in {n * HEARTBEAT_MS * 1.5 / 1000 + s.timeout_s:.2f} s at "
                          f"heartbeat_ms={HEARTBEAT_MS}")
    # Theil-Sen: the median of the slopes between every pair of heartbeats, so one heartbeat held up
    # by the host (or the port) does not move the estimate; a chip's own clock error does
    period = statistics.median((st[j][0] - st[i][0]) / (j - i) for i in range(len(st))
                               for j in range(i + 1, len(st))) * 1000
    tol = 0.05 * HEARTBEAT_MS + s.slack_ms / 2
    require(abs(period - HEARTBEAT_MS) <= tol, f"period {period:.1f} ms over {len(st)} heartbeats "
                                               f"({HEARTBEAT_MS} ± {tol:.1f} ms)")
    m = st[-1][1]
    require(m.state == ChipState.IDLE, f"state {ChipState(m.state).name}")
    require(bool(m.flags & StatusFlag.CONFIGURED), f"flags {StatusFlag(m.flags)!r}")
    require(m.flags & ~0x0F == 0, f"reserved STATUS flag bits set: 0x{m.flags:02X}")
    up = [x.uptime_s for _, x in st]
    require(up == sorted(up), f"uptime_s goes backwards: {up}")
    return f"period {period:.1f} ms over {len(st)} heartbeats, rx_errors {m.rx_errors}"


@check("4.6, 4.11", "CONFIG with a field out of range: NACK BAD_VALUE",
       "the chip accepts a configuration it cannot honour",
       "validate CONFIG before applying it: range > 3, filter > 3, rate_hz 0 or > 4000 -> NACK 3 BAD_VALUE")
def c_config_bad_value(s: Session):
    s.ensure_idle()
    for cfg in (Config(s.node, range=7), Config(s.node, rate_hz=0), Config(s.node, rate_hz=4001),
                Config(s.node, filter=4)):
        ans = s.request(cfg)
        require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_VALUE)], f"{cfg} answered {ans}")


@check("4.6, 4.15", "a capability the chip lacks: NACK UNSUPPORTED (CONFIG range, CAL_WRITE store)",
       "the chip claims to do what it cannot, or refuses what it advertises",
       "range != 0 without MULTI_RANGE and CAL_WRITE flags bit 0 without CAL_STORAGE -> NACK 5 "
       "UNSUPPORTED; with the capability, ACK")
def c_unsupported(s: Session):
    s.ensure_idle()
    caps = int(s.info.capabilities)
    ans = s.request(Config(s.node, range=1, heartbeat_ms=HEARTBEAT_MS))
    s.request(Config(s.node, range=0, heartbeat_ms=HEARTBEAT_MS))  # back to ±2 g whatever happened
    ok = acked(ans, s.node, MsgType.CONFIG) if caps & Capability.MULTI_RANGE else \
        ans == [Nack(s.node, MsgType.CONFIG, NackReason.UNSUPPORTED)]
    require(ok, f"CONFIG range 1 ({'with' if caps & Capability.MULTI_RANGE else 'without'} "
                f"MULTI_RANGE) answered {ans}")
    if not caps & Capability.CAL_STORAGE:
        ans = s.request(CalWrite(s.node, axis=0, flags=1, offset_q4=0, sensitivity=1024.0))
        require(ans == [Nack(s.node, MsgType.CAL_WRITE, NackReason.UNSUPPORTED)],
                f"CAL_WRITE store without CAL_STORAGE answered {ans}")
    return f"capabilities {Capability(caps & 0x3F)!r}"


@check("4, 4.6, 8", "an undefined type addressed to the chip: NACK UNKNOWN_COMMAND",
       "a host cannot tell a chip that lacks a command from a lost frame",
       "NACK reason 1 UNKNOWN_COMMAND, command = the type code, for an undefined type addressed to the chip")
def c_unknown(s: Session):
    s.ensure_idle()
    ans = s.raw(0x3F, s.node, b"")
    require(ans == [Nack(s.node, 0x3F, NackReason.UNKNOWN_COMMAND)], f"answered {ans}")


@check("8, 8.1", "a chip -> host type addressed to the chip is ignored (no NACK)",
       "on a shared bus the chip answers other chips' frames (a NACK storm)",
       "drop decoded chip -> host types (0x01..0x0F) silently, whatever their node")
def c_chip_type_ignored(s: Session):
    s.ensure_idle()
    ans = s.silent(lambda: s.port.send_raw(MsgType.STATUS, s.node, bytes(8)))
    require(ans == [], f"a STATUS frame addressed to the chip was answered {ans}")


@check("4.6", "a payload of the wrong length: NACK BAD_LENGTH",
       "the chip acts on truncated or padded commands",
       "compare the payload length with §4's size for the type; on a mismatch NACK 2 BAD_LENGTH")
def c_bad_length(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.START, s.node, b"\x01")
    require(ans == [Nack(s.node, MsgType.START, NackReason.BAD_LENGTH)], f"answered {ans}")


@check("12, 4.6", "a frame of another protocol version: NACK BAD_VERSION, in version 1",
       "a host of another version cannot learn that the chip speaks v1",
       "do not decode a frame whose version is not 1; NACK 6 BAD_VERSION in the chip's own version")
def c_bad_version(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.GET_INFO, s.node, b"", version=PROTOCOL_VERSION + 1)
    require(ans == [Nack(s.node, MsgType.GET_INFO, NackReason.BAD_VERSION)], f"answered {ans}")


@check("4.6, 4.15", "a field the decoder rejects (CAL_READ axis 3): NACK BAD_VALUE",
       "the chip reads or writes out of bounds on a bad field",
       "range-check every field on decode; NACK 3 BAD_VALUE")
def c_bad_field(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.CAL_READ, s.node, b"\x03")
    require(ans == [Nack(s.node, MsgType.CAL_READ, NackReason.BAD_VALUE)], f"answered {ans}")


@check("4.15, 4.7", "CAL_WRITE then CAL_READ gives the calibration back (CAL_DATA)",
       "calibration written by the host is lost or corrupted",
       "keep the CAL_WRITE fields per axis and answer CAL_READ with CAL_DATA carrying them")
def c_calibration(s: Session):
    s.ensure_idle()
    for axis, off, sens in ((1, -21, 1003.5), (2, 37, 998.25)):
        ans = s.request(CalWrite(s.node, axis=axis, flags=0, offset_q4=off, sensitivity=sens))
        require(acked(ans, s.node, MsgType.CAL_WRITE), f"CAL_WRITE answered {ans}")
        ans = s.request(CalRead(s.node, axis=axis))
        require(ans == [CalData(s.node, axis=axis, flags=0, offset_q4=off, sensitivity=sens)],
                f"CAL_READ axis {axis} answered {ans}")


@check("6.4, 6.3, 4.4, 8.1", "damaged serial input is dropped silently, counted in rx_errors, and the chip recovers",
       "line noise makes the chip act, hang, or go unreported",
       "drop every run that fails COBS/CRC/length without answering; count each in rx_errors "
       "(saturating); resynchronise at the next 0x00", transport="serial")
def c_bad_input_serial(s: Session):
    s.ensure_idle()
    before = s.status().rx_errors
    body = HEADER.pack(PROTOCOL_VERSION, MsgType.GET_INFO, s.node)
    bad_crc = cobs.encode(body + ((crc16_ccitt_false(body) ^ 0x0100).to_bytes(2, "big"))) + b"\x00"
    junk = [b"\x05\x01\x02\x03\x00", bad_crc, b"\x01" * 1100 + b"\x00", b"\x03\x01\x02\x00"]
    ans = s.silent(lambda: [s.port.send_bytes(j) for j in junk])
    require(ans == [], f"answered damaged input with {ans}")
    ans = s.request_info(s.node)  # answered only once every byte before it was processed
    require(len(ans) == 2, f"no answer to GET_INFO after the damage: {ans}")
    after = s.status().rx_errors  # a heartbeat sent after that answer
    require(after - before == len(junk) or after == 255, f"rx_errors {before} -> {after}, expected +{len(junk)}")
    return f"rx_errors {before} -> {after}"


@check("7.1, 7.2", "frames that are not capsheet frames are not answered, and the chip recovers",
       "foreign traffic on the bus makes the chip act",
       "accept only 29-bit identifiers of version 1; ignore standard frames", transport="can")
def c_bad_input_can(s: Session):
    s.ensure_idle()
    if not isinstance(s.port.transport, AuditedCanTransport):
        raise Skip("needs AuditedCanTransport to send standard-identifier frames")
    ans = s.silent(lambda: s.port.transport.send_frame(0x123, b"\x01\x02", extended=False))
    require(ans == [], f"answered a standard-identifier frame with {ans}")
    ans = s.request_info(s.node)
    require(len(ans) == 2, f"no answer to GET_INFO afterwards: {ans}")


# ---------------------------------------------------------------------------------------------
# STREAMING: SYNC, SAMPLE
# ---------------------------------------------------------------------------------------------

@check("4.12", "START: ACK, the chip is STREAMING; START again is ACKed too",
       "the chip cannot be started, or a repeated START is refused",
       "on START in IDLE: ACK and enter STREAMING; in STREAMING: ACK (idempotent)")
def c_start(s: Session):
    s.ensure_idle()
    for _ in range(2):
        ans = s.request(Start(s.node))
        require(acked(ans, s.node, MsgType.START), f"answered {ans}")
    ans = s.request_info(s.node)
    require(len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.STREAMING, f"GET_INFO: {ans}")


@check("5.1, 4.3, 4.9", "SYNC -> exactly one SAMPLE with the SYNC's counter (within 2 ms: a SHOULD, reported)",
       "the host cannot group samples into snapshots (wrong counter, missing or duplicate answers)",
       "answer each SYNC with one SAMPLE carrying its counter (u16 little-endian), within 2 ms")
def c_sync(s: Session):
    s.to_streaming()
    lat, samples = [], []
    for c in range(100, 130):
        s.drain()
        t0 = s.port.send(Sync(counter=c))
        got = s.collect(s.answer_s, lambda ms: any(isinstance(m, Sample) for m in ms))
        smp = [(t, m) for t, m in got if isinstance(m, Sample)]
        require(len(smp) == 1, f"SYNC {c}: {len(smp)} SAMPLE")
        require(smp[0][1].counter == c, f"SYNC 0x{c:04X} answered with counter 0x{smp[0][1].counter:04X}")
        lat.append(smp[0][0] - t0)
        samples.append(smp[0][1])
    extra = [m for _, m in s.collect(s.timeout_s) if isinstance(m, Sample)]
    require(not extra, f"SYNCs answered twice: {len(extra)} extra SAMPLE (counters {[m.counter for m in extra][:5]})")
    med = statistics.median(lat) * 1000
    limit = SYNC_REPLY_DEADLINE_S * 1000 + s.slack_ms
    timing = f"median {med:.2f} ms, max {max(lat) * 1000:.2f} ms (host-measured, includes the port)"
    if med > limit:  # §5.1: the chip SHOULD answer within 2 ms: reported, not a FAIL
        return f"{SHOULD_NOT_MET} the median SYNC->SAMPLE is over 2 ms + {s.slack_ms:g} ms slack: {timing}"
    return timing


def _samples(s: Session, counters) -> list[Sample]:
    """One SYNC per counter; the SAMPLE answering each (a late duplicate of an earlier one is skipped)."""
    out = []
    for c in counters:
        s.drain()
        s.port.send(Sync(counter=c))
        got = s.collect(s.answer_s, lambda ms, c=c: any(isinstance(m, Sample) and m.counter == c for m in ms))
        smp = [m for _, m in got if isinstance(m, Sample)]
        match = [m for m in smp if m.counter == c]
        require(bool(match), f"SYNC 0x{c:04X} answered with {smp or 'nothing'}")
        out.append(match[0])
    return out


@check("5.2, 4.3", "SAMPLE at rest: |a| = 1 g ± 0.5 g, SATURATED exactly at the rails, not INVALID",
       "the sensor is dead, disconnected or mis-scaled while the chip reports it healthy",
       "put the ADC's counts (12-bit two's complement, 1024/g at ±2 g) in the sample word; set SATURATED "
       "when an axis is at −2048 or 2047; INVALID when the sensor did not answer (and enter FAULT)")
def c_sample_word(s: Session):
    s.to_streaming()
    seen = _samples(s, range(200, 216))
    per_g = 1024  # the run configures range 0 (±2 g)
    mags = [math.sqrt(m.x ** 2 + m.y ** 2 + m.z ** 2) / per_g for m in seen]
    mean = statistics.fmean(mags)
    for m in seen:
        rails = any(v in (-2048, 2047) for v in (m.x, m.y, m.z))
        require(rails == bool(m.status & SampleStatus.SATURATED),
                f"SATURATED {'clear' if rails else 'set'} for counts {(m.x, m.y, m.z)}")
        require(not m.status & SampleStatus.INVALID, f"INVALID sample {(m.x, m.y, m.z)} while STREAMING")
    require(0.5 <= mean <= 1.5, f"|a| = {mean:.3f} g at rest (counts {(seen[-1].x, seen[-1].y, seen[-1].z)}, "
                                f"status 0x{seen[-1].status:X}): a chip at rest measures gravity")
    return f"|a| = {mean:.3f} g, last {(seen[-1].x, seen[-1].y, seen[-1].z)} status 0x{seen[-1].status:X}"


@check("5.1, 5.2", "a repeated value is flagged STALE: 20 samples do not all repeat unflagged",
       "the chip reports old conversions as fresh (a frozen or dead sensor looks alive)",
       "answer SYNC with a conversion finished since the previous SYNC; if there is none, repeat the "
       "last value with status STALE (bit 2)")
def c_stale(s: Session):
    s.to_streaming()
    seen = _samples(s, range(300, 320))
    values = {(m.x, m.y, m.z) for m in seen}
    fresh = [m for m in seen if not m.status & SampleStatus.STALE]
    reps = sum(1 for a, b in zip(seen, seen[1:]) if (a.x, a.y, a.z) == (b.x, b.y, b.z)
               and not b.status & SampleStatus.STALE)
    require(len(values) > 1 or len(fresh) <= 1, f"{len(seen)} samples all {seen[0].x, seen[0].y, seen[0].z}, "
                                                f"none flagged STALE")
    return f"{len(values)} distinct values in {len(seen)} samples, {reps} unflagged repeats"


@check("4.9, 5.1, 8.1", "SYNC counter wraparound 0xFFFF -> 0 is not a miss; a gap is counted in missed_syncs",
       "the host's lost-sample accounting is wrong",
       "compare counters modulo 2^16: add (counter − last − 1) mod 2^16 to missed_syncs when below "
       "0x7FFF; START forgets the last counter")
def c_wraparound(s: Session):
    s.to_streaming()
    st0 = s.status().missed_syncs
    if st0 > 250:  # near saturation: start from a fresh count
        s.to_idle()
        s.to_streaming()
        st0 = s.status().missed_syncs
    s.ensure_idle()
    ans = s.request(Start(s.node))  # START forgets the last counter (§8.1)
    require(acked(ans, s.node, MsgType.START), f"START answered {ans}")
    _samples(s, (0xFFFD, 0xFFFE, 0xFFFF, 0, 1))
    st1 = s.status().missed_syncs
    require(st1 == st0, f"missed_syncs {st0} -> {st1} over a wraparound without gaps (START, 0xFFFD..0x0001)")
    _samples(s, (2, 5))  # 3 and 4 missed
    st2 = s.status().missed_syncs
    require(st2 - st1 == 2, f"missed_syncs {st1} -> {st2} after skipping 2 counters")
    return f"missed_syncs {st0} -> {st1} -> {st2}"


@check("8, 4.10, 4.11", "CONFIG and ASSIGN while STREAMING: NACK BAD_STATE",
       "the chip changes configuration or address mid-stream",
       "refuse CONFIG, ASSIGN, CAL_WRITE while STREAMING with NACK 4 BAD_STATE (STOP first)")
def c_bad_state_streaming(s: Session):
    s.to_streaming()
    ans = s.request(Config(s.node))
    require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_STATE)], f"CONFIG answered {ans}")
    ans = s.request(Assign(s.node, new_node=s.node, link=0, uid_low=s.uid & 0xFFFFFFFF))
    require(ans == [Nack(s.node, MsgType.ASSIGN, NackReason.BAD_STATE)], f"ASSIGN answered {ans}")


@check("4.12", "STOP: ACK, back to IDLE, SYNC no longer answered; STOP again is ACKed",
       "the chip cannot be stopped and keeps loading the bus",
       "on STOP in STREAMING: ACK and enter IDLE; in IDLE: ACK")
def c_stop(s: Session):
    s.to_streaming()
    for _ in range(2):
        ans = s.request(Stop(s.node))
        require(acked(ans, s.node, MsgType.STOP), f"answered {ans}")
    ans = s.silent(Sync(counter=7))
    require(ans == [], f"SYNC after STOP answered {ans}")


# ---------------------------------------------------------------------------------------------
# Broadcast (only with --allow-broadcast: they address every chip on the port)
# ---------------------------------------------------------------------------------------------

@check("3.1, 8", "a broadcast the state table refuses gets no NACK (START broadcast in BOOT)",
       "one broadcast causes a NACK from every chip (a storm)",
       "for a broadcast (node 0) frame, refuse silently: never NACK BAD_STATE to a broadcast", broadcast=True)
def c_broadcast_silent(s: Session):
    s.fresh_boot()
    ans = s.silent(Start(0))
    require(ans == [], f"answered {ans}")


@check("4.12", "broadcast START and STOP address every assigned chip: each ACKs",
       "a host cannot start a sheet with one frame", "act on START/STOP addressed to node 0 like on your own",
       broadcast=True)
def c_broadcast_start(s: Session):
    s.ensure_idle()
    ans = s.request(Start(0))
    require(acked(ans, s.node, MsgType.START), f"START broadcast answered {ans}")
    ans = s.request(Stop(0))
    require(acked(ans, s.node, MsgType.STOP), f"STOP broadcast answered {ans}")


# ---------------------------------------------------------------------------------------------
# Everything the chip sent during the run
# ---------------------------------------------------------------------------------------------

@check("6.1, 6.2, 6.3, 7.1, 7.2, 4.8", "every frame from the chip decoded (COBS, CRC / identifier, priority, "
       "lengths); no SNAPSHOT from a chip",
       "a host drops the chip's frames (wrong CRC variant, framing, identifier layout or priority)",
       "CRC-16/CCITT-FALSE (check 0x29B1) over header + payload, MSB first, then COBS and 0x00; on CAN "
       "the §4 priority in bits 28..26 and classic frames for payloads ≤ 8 bytes")
def c_framing(s: Session):
    p = s.port
    require(p.frames > 0 or p.damaged > 0, "nothing received")
    if p.damaged and not p.lossy:
        raise CheckFailed(f"{p.damaged} of {p.damaged + p.frames} frames did not decode "
                          f"({dict(p.damage)}): the chip's framing, not the port")
    bad = getattr(p.transport, "bad_ids", [])
    require(not bad, "; ".join(bad[:3]))
    if p.damaged:
        raise PortLost(f"{p.damaged} of {p.damaged + p.frames} frames did not decode ({dict(p.damage)})")
    return f"{p.frames} frames"


def _from(s: Session, raw: bytes) -> bool:
    """The serial frame came from a node id the chip under test used (header intact)."""
    try:
        body = cobs.decode(raw.rstrip(b"\x00"))
    except cobs.DecodeError:
        return False
    return len(body) >= 4 and HEADER.unpack_from(body)[2] in s.my_nodes


def _canonical_serial(raw: bytes) -> str | None:
    msg = decode_frame(raw.rstrip(b"\x00"))
    if isinstance(msg, DecodeError):
        return None
    ref = encode(msg)
    return None if ref == raw else f"{msg.TYPE.name}: sent {raw.hex(' ')}, reference {ref.hex(' ')}"


@check("2, 9, 4.5", "every frame is byte-identical to the reference encoding of its fields "
       "(reserved bits 0, little-endian)",
       "the chip sends non-zero reserved bits or a non-canonical encoding; a future version may give them meaning",
       "send reserved bits and bytes as 0 (ACK detail, flags, capabilities); encode as the golden vectors (§9)")
def c_canonical(s: Session):
    t = s.port.transport
    bad, n = [], 0
    if s.port.kind == "serial":
        for raw in list(s.port.raw):
            if not _from(s, raw):
                continue
            n += 1
            d = _canonical_serial(raw)
            if d:
                bad.append(d)
    elif isinstance(t, AuditedCanTransport):
        from protocol.can import to_can
        for aid, data, fd in list(t.raw):
            msg = decode_can(aid, data, is_fd=fd)
            if isinstance(msg, DecodeError) or not isinstance(msg, Message) or msg.node not in s.my_nodes:
                continue
            n += 1
            ref = to_can(msg, fd=fd)
            if ref.data != data or (ref.arbitration_id & 0x03FFFFFF) != (aid & 0x03FFFFFF):
                bad.append(f"{msg.TYPE.name}: sent {aid:08X}#{data.hex()}, reference "
                           f"{ref.arbitration_id:08X}#{ref.data.hex()}")
    else:
        raise Skip("the port keeps no raw frames")
    require(not bad, f"{len(bad)} of {n} frames differ from the reference encoding; first: {bad[0] if bad else ''}")
    acks = [m for m in s.acks if m.detail != 0]
    require(not acks, f"{len(acks)} ACK with detail != 0 (reserved in v1), first: {acks[:1]}")
    return f"{n} frames compared"


@check("7.3", "every frame from the chip decodes with the DBC (cantools) to the same fields",
       "CAN tools using protocol/capsheet.dbc misread the chip",
       "use the §7.1 identifiers and §4 layouts (the DBC is generated from them)", transport="can")
def c_dbc(s: Session):
    t = s.port.transport
    if not isinstance(t, AuditedCanTransport):
        raise Skip("needs AuditedCanTransport")
    from protocol.dbc import load_database
    db = load_database()
    bad, n = [], 0
    for aid, data, fd in list(t.raw):
        msg = decode_can(aid, data, is_fd=fd)
        if not isinstance(msg, (Sample, Ack, Nack, Status, Announce, Info)) or msg.node not in s.my_nodes:
            continue
        n += 1
        try:
            sig = db.get_message_by_frame_id(aid).decode(data, decode_choices=False)
        except Exception as exc:  # noqa: BLE001 - cantools raises several kinds
            bad.append(f"{aid:08X}#{data.hex()}: {exc}")
            continue
        diff = {k: (v, getattr(msg, k)) for k, v in sig.items()
                if hasattr(msg, k) and not math.isclose(float(v), float(getattr(msg, k)), rel_tol=1e-6)}
        if diff:
            bad.append(f"{msg.TYPE.name} {aid:08X}#{data.hex()}: DBC vs decoder {diff}")
    require(not bad, f"{len(bad)} of {n} frames: {bad[0] if bad else ''}")
    return f"{n} frames decoded by the DBC"


def table() -> str:
    """The checks as the markdown table of docs/conformance.md."""
    lines = ["| # | clauses | check | a FAIL means | fix in the chip |", "|---|---|---|---|---|"]
    for c in CHECKS:
        only = f" *({c.transport} only)*" if c.transport else ""
        bc = " *(--allow-broadcast)*" if c.broadcast else ""
        cells = [str(c.number), c.clause, c.title + only + bc, c.meaning, c.fix]
        lines.append("| " + " | ".join(x.replace("|", "\\|") for x in cells) + " |")
    lines += ["", "Clauses without a check of their own, and why:", ""]
    lines += [f"- §{k}: {v}" for k, v in INFORMATIVE.items()]
    return "\n".join(lines) + "\n"
