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
"""

from __future__ import annotations

import math
import statistics
import struct
import time
from dataclasses import dataclass
from typing import Callable

from cobs import cobs

from host.transport.ports import CanTransport
from protocol.can import decode_can
from protocol.crc import crc16_ccitt_false
from protocol.framing import HEADER, DecodeError, decode_frame, encode, encode_frame
from protocol.messages import (NODE_PROVISIONAL_MAX, NODE_PROVISIONAL_MIN, PROTOCOL_VERSION, RESERVED_CAPABILITIES,
                               Ack, Announce, Assign, CalData, CalRead, CalWrite, Capability, ChipState, Config,
                               GatewayFlag, GatewayInfo, GetInfo, Info, Message, MsgType, Nack, NackReason, Reset,
                               Sample, Snapshot, Start, Status, StatusFlag, Stop, Sync, provisional_node,
                               TIME_UNKNOWN, ConfigImu, ConfigImuFlag, ImuSample, SampleFormat,
                               CAL_BLOCK_SIZE, CalBlock, CalImuData, CalImuRead, CalImuWrite, cal_block_nominal)
from protocol.constants import SampleStatus
from protocol.state import ANNOUNCE_PERIOD_S, GATEWAY_HEARTBEAT_MS, SYNC_REPLY_DEADLINE_S, TIMER_TOLERANCE

from .session import HEARTBEAT_MS, acked, CheckFailed, PortLost, RunAborted, Session, Skip, require

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


def _should(s: Session, ok: bool, what: str, detail: str) -> str:
    """The detail of a check whose MUST passed, with its SHOULD reported."""
    return detail if ok else f"{SHOULD_NOT_MET} {what}; {detail}"


# ---------------------------------------------------------------------------------------------
# Discovery, identity, BOOT
# ---------------------------------------------------------------------------------------------

def _discover(s: Session, kind: str) -> str:
    """Broadcast GET_INFO; the node under test is the first ``kind`` ("chip" or "gateway") to answer
    (or ``--uid``). Counts what answered, by uid: a provisional id changes every second, a uid never."""
    s.drain()
    s.port.send(GetInfo(0))
    window = max(1.0, 2 * s.timeout_s)  # every node on the port answers: note every uid and node id heard

    def found(ms):
        return any(v == kind and (s.uid is None or u == s.uid) for u, v in s.uids_heard.items())
    s.collect(window, lambda ms: found(ms))
    s.collect(min(0.3, s.timeout_s))  # the other nodes' answers: their node ids are in use
    kinds = s.uids_heard
    mine = [u for u, v in kinds.items() if v == kind and (s.uid is None or u == s.uid)]
    chips = sum(v == "chip" for v in kinds.values())
    gws = sum(v == "gateway" for v in kinds.values())
    heard = f"{chips} chip(s) and {gws} gateway(s) answered (by uid)"
    if not mine:
        if s.uid is not None:
            raise CheckFailed(f"no {kind} with uid 0x{s.uid:016X} answered a broadcast GET_INFO; {heard}")
        lost = f" ({s.port.lost} damaged frames arrived: see §6.2)" if s.port.lost else ""
        raise CheckFailed(f"no {kind} answered a broadcast GET_INFO with ANNOUNCE then INFO; {heard}{lost}")
    s.uid = mine[0]
    s.cur = s.node_of_uid[s.uid]
    got = s.request_info(s.cur)  # its own ANNOUNCE + INFO, addressed: the order is checked here
    infos = [m for m in got if isinstance(m, Info)]
    require(len(got) >= 2 and isinstance(got[0], Announce) and infos and infos[0].node == got[0].node,
            f"GET_INFO to node 0x{s.cur:04X} answered {got} (ANNOUNCE then INFO, from one node id)")
    s.info = s.first_info = infos[0]
    if s.node is None:
        s.node = s.pick_node()
    elif s.node in s.nodes_seen and s.node != s.cur:
        raise RunAborted(f"--node 0x{s.node:04X} is in use by another node on the port; omit --node to pick "
                         f"a free one")
    return (f"uid 0x{s.uid:016X}, node 0x{s.cur:04X}, state {s.info.state.name}; {heard}; the run uses node "
            f"0x{s.node:04X}")


@check("4.13, 4.1", "GET_INFO (broadcast) is answered with ANNOUNCE then INFO",
       "the chip cannot be discovered: a host never finds it",
       "answer GET_INFO addressed to node 0 or to the chip, in every state, with ANNOUNCE then INFO "
       "(two frames, in that order, from the current node id)")
def c_discover(s: Session):
    detail = _discover(s, "chip")
    g = s.packing_gateway_for_any()
    if g is not None:
        s.link = g.first_link()
        detail += f"; behind {g.label()}, which packs: the run gives the chip link {s.link}"
    if s.sync_gateway is not None:
        detail += f"; {s.sync_gateway.label()} is the segment's SYNC source: the SYNC checks use its counters"
    return detail


@check("4.2", "INFO: protocol version 1, 12-bit ADC, reserved capability bits 0, not a gateway",
       "the host cannot trust the chip's self-description (version, ADC, capabilities)",
       "send protocol_version 1 and adc_bits 12; send capability bits 8..15 as 0 and bit 6 (GATEWAY) "
       "and 7 (SYNC_SOURCE) as 0 on a chip")
def c_info(s: Session):
    s.need_chip()
    i = s.info
    require(i.protocol_version == PROTOCOL_VERSION, f"protocol_version {i.protocol_version}")
    require(i.adc_bits == 12, f"adc_bits {i.adc_bits}")
    caps = int(i.capabilities)
    require(caps & RESERVED_CAPABILITIES == 0, f"reserved capability bits set: 0x{caps:04X}")
    require(not caps & (Capability.GATEWAY | Capability.SYNC_SOURCE), f"a chip with gateway bits: 0x{caps:04X}")
    return f"firmware {i.fw_major}.{i.fw_minor}.{i.fw_patch}, capabilities {Capability(caps)!r}"


@check("4.14, 3.1", "RESET: ACK from the current node, then ANNOUNCE + INFO in BOOT, same uid",
       "a host cannot bring the chip back to a known state (and its uid is not stable)",
       "on RESET: ACK from the current node id, forget assignment and configuration, enter BOOT, send "
       "ANNOUNCE (the same factory uid) then INFO (state 0)", profiles=PROFILES)
def c_reset(s: Session):
    if s.profile == "gateway":
        s.assign_gateway()
    else:
        s.assign_without_reset()  # an assigned chip does not re-announce: only the RESET can cause the ANNOUNCE
    before = s.cur
    n = 4 if s.profile == "gateway" else 3
    ans = s.request(Reset(s.cur), n, keep=(Announce, Info, GatewayInfo))
    require(len(ans) >= 3, f"expected ACK, ANNOUNCE, INFO; got {ans}")
    require(acked(ans[:1], before, MsgType.RESET), f"first answer {ans[0]}")
    require(isinstance(ans[1], Announce) and ans[1].uid == s.uid, f"second answer {ans[1]} (uid 0x{s.uid:016X})")
    require(isinstance(ans[2], Info) and ans[2].state == ChipState.BOOT and ans[2].node == ans[1].node,
            f"third answer {ans[2]}")
    if s.profile == "gateway":
        require(len(ans) == 4 and isinstance(ans[3], GatewayInfo) and ans[3].node == ans[1].node,
                f"a gateway's INFO is followed by GATEWAY_INFO (§13.1); got {ans}")
    s.cur = ans[1].node


@check("3.2", "an unassigned node speaks from a provisional node id (0x8000..0xFFFE; the formula: a SHOULD)",
       "an unassigned node collides with assigned nodes' ids",
       "in BOOT, send from provisional_node(uid, salt) (§3.2), never from an assigned id",
       level="MUST; SHOULD reported", profiles=PROFILES)
def c_provisional(s: Session):
    s.fresh_boot()
    require(NODE_PROVISIONAL_MIN <= s.cur <= NODE_PROVISIONAL_MAX, f"node 0x{s.cur:04X}")
    rec = provisional_node(s.uid, 0)
    return _should(s, s.cur == rec, f"0x{s.cur:04X} is not provisional_node(uid, 0) = 0x{rec:04X} after RESET",
                   f"node 0x{s.cur:04X}")


@check("8.2", "a command not allowed in BOOT is refused: NACK BAD_STATE",
       "a host cannot tell that the chip ignored a command (START before ASSIGN)",
       "for a (state, command) pair not in the §8.2 table, addressed to the chip: NACK reason 4 BAD_STATE")
def c_bad_state_boot(s: Session):
    s.fresh_boot()
    ans = s.request(Start(s.cur))
    require(ans == [Nack(s.cur, MsgType.START, NackReason.BAD_STATE)], f"START in BOOT answered {ans}")


@check("4.10", "ASSIGN whose uid_low is another node's is ignored silently",
       "two nodes sharing a provisional id would both take the assignment",
       "compare uid_low with the low 32 bits of the uid; on a mismatch send nothing and change nothing",
       profiles=PROFILES)
def c_assign_wrong_uid(s: Session):
    s.fresh_boot()
    other = (s.uid ^ 0x5A5A5A5A) & 0xFFFFFFFF
    ans = s.silent(Assign(s.cur, new_node=s.node, link=s.link, uid_low=other))
    require(ans == [], f"answered {ans}")
    ans = s.request_info(s.cur)
    infos = [m for m in ans if isinstance(m, Info)]
    require(infos and infos[0].state == ChipState.BOOT,
            f"after a foreign ASSIGN, GET_INFO to the provisional id answered {ans}")


@check("4.10, 3.3", "ASSIGN: ACK from the new node id; the node is IDLE there",
       "the node cannot be assigned, or answers from the wrong node id",
       "on ASSIGN (addressed, uid_low matching): take new_node (and link), ACK from new_node, enter IDLE",
       profiles=PROFILES)
def c_assign(s: Session):
    s.fresh_boot()
    link = 0xFFFF if s.profile == "gateway" else s.link
    ans = s.request(Assign(s.cur, new_node=s.node, link=link, uid_low=s.uid & 0xFFFFFFFF))
    require(acked(ans, s.node, MsgType.ASSIGN), f"answered {ans}")
    s.cur = s.node
    ans = s.request_info(s.node)
    infos = [m for m in ans if isinstance(m, Info)]
    require(infos and infos[0].state == ChipState.IDLE, f"GET_INFO: {ans}")


#: re-announces timed by check 8 after the boot announce (Theil-Sen over these and the boot's)
REANNOUNCES = 3


def theil_sen_period(times) -> float:
    """The period of events at ``times`` (s, in order, one per period): the median of the slopes
    between every pair, so one event read late (an outlier) does not move it, a clock's own error
    does."""
    t = list(times)
    if len(t) < 2:
        raise ValueError(f"Invalid times: {len(t)} event(s) (need at least 2)")
    return statistics.median((t[j] - t[i]) / (j - i) for i in range(len(t)) for j in range(i + 1, len(t)))


@check("3.2, 14", "an unassigned node repeats ANNOUNCE + INFO every 1 s (± 5 %)",
       "a host that starts after the node never hears it (or is flooded)",
       "in BOOT, resend ANNOUNCE then INFO every 1 s from a free-running time base (the next deadline is the "
       "previous one + 1 s)", profiles=PROFILES)
def c_reannounce(s: Session):
    s.fresh_boot()
    t_boot = s.boot_t
    window = ANNOUNCE_PERIOD_S * (REANNOUNCES + 0.6)
    got = s.collect(window, lambda ms: sum(isinstance(m, Announce) for m in ms) >= REANNOUNCES
                    and isinstance(ms[-1], (Info, GatewayInfo)))
    times = [t_boot] + [t for t, m in got if isinstance(m, Announce)]
    require(len(times) >= REANNOUNCES + 1, f"{len(times) - 1} re-ANNOUNCE within {window:.1f} s of a RESET")
    periods = [b - a for a, b in zip(times, times[1:])]
    # Theil-Sen, as for the heartbeat: the median of the slopes between every pair of announces. The
    # deadlines are free-running (§14), so one announce held up by the host or the port is an outlier
    # the median drops; a chip's own period error moves every slope. (The mean of two periods failed
    # a healthy chip on a host that read the last announce 143 ms late: 1.003, 1.143 s.)
    period = theil_sen_period(times)
    tol = TIMER_TOLERANCE * ANNOUNCE_PERIOD_S + s.slack_ms / 1000
    require(abs(period - ANNOUNCE_PERIOD_S) <= tol, f"re-announce period {period:.3f} s (1 s ± {tol * 1000:.0f} ms; "
                                                    f"periods {', '.join(f'{p:.3f}' for p in periods)} s)")
    ms = [m for _, m in got]
    pairs = [(a, b) for a, b in zip(ms, ms[1:]) if isinstance(a, Announce)]
    require(all(isinstance(b, Info) and b.node == a.node for a, b in pairs), f"re-ANNOUNCE not followed by INFO: {ms}")
    return f"periods {', '.join(f'{p:.3f}' for p in periods)} s"


@check("3.3", "in BOOT, an ASSIGN to the previous round's provisional id is taken",
       "a host whose ASSIGN crossed the node's next ANNOUNCE on the wire loses the node for a round "
       "(or for good, on a busy bus)",
       "keep the provisional id of the round before; take an ASSIGN addressed to it when uid_low matches",
       profiles=PROFILES)
def c_previous_id(s: Session):
    s.fresh_boot()
    first = s.cur
    got = s.collect(ANNOUNCE_PERIOD_S * 1.6, lambda ms: any(isinstance(m, Announce) for m in ms))
    require(any(isinstance(m, Announce) for _, m in got), "no re-ANNOUNCE within 1.6 s of a RESET")
    require(s.cur != first, f"the re-ANNOUNCE came from the same id 0x{s.cur:04X}: no previous id to assign at")
    link = 0xFFFF if s.profile == "gateway" else s.link
    ans = s.request(Assign(first, new_node=s.node, link=link, uid_low=s.uid & 0xFFFFFFFF))
    require(acked(ans, s.node, MsgType.ASSIGN), f"§3.3: ASSIGN to the previous provisional id 0x{first:04X} (now "
                                               f"0x{s.cur:04X}) answered {ans}")
    s.cur = s.node
    return f"ASSIGN to 0x{first:04X} taken after the node moved to its next id"


# ---------------------------------------------------------------------------------------------
# IDLE: configuration, NACKs, calibration, heartbeat
# ---------------------------------------------------------------------------------------------

@check("4.11, 8.3", "CONFIG (valid) is acknowledged, also the same one again",
       "the chip cannot be configured", "ACK a CONFIG whose fields are in range, in IDLE and FAULT")
def c_config(s: Session):
    s.ensure_idle()
    for _ in range(2):  # the same CONFIG again is ACKed too
        ans = s.request(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=HEARTBEAT_MS))
        require(acked(ans, s.node, MsgType.CONFIG), f"answered {ans}")


@check("8.4, 4.4", f"STATUS every heartbeat_ms ({HEARTBEAT_MS} ms ± 5 % + slack/2); an accepted CONFIG restarts "
       "the period; IDLE, CONFIGURED",
       "the host's liveness monitoring misjudges the chip (its clock or scheduler is off)",
       "send STATUS every heartbeat_ms from a free-running time base (a hardware counter, not a count of "
       "timer interrupts); at an accepted CONFIG start the period again; set CONFIGURED after CONFIG")
def c_heartbeat(s: Session):
    """The period by Theil-Sen over 9 heartbeats; the restart by a CONFIG sent half a period after a
    STATUS: a chip that restarts sends the next STATUS a whole period after the CONFIG, one that does
    not half a period after it. Lateness (the host's, the port's) only makes that gap longer, so the
    bound is one-sided: the suite passes a conforming chip on a loaded machine."""
    s.ensure_idle()
    gaps = []
    for _ in range(3):
        st = s.statuses(1)
        require(bool(st), f"no STATUS within {max(1.5, 3 * s.timeout_s):.1f} s")
        time.sleep(HEARTBEAT_MS / 2000)
        s.drain()
        s.port.send(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=HEARTBEAT_MS))
        def after_ack(ms):
            k = next((i for i, m in enumerate(ms) if acked([m], s.node, MsgType.CONFIG)), None)
            return k is not None and any(isinstance(m, Status) for m in ms[k + 1:])
        got = s.collect(s.answer_s, after_ack)
        k = next((i for i, (_, m) in enumerate(got) if acked([m], s.node, MsgType.CONFIG)), None)
        sts = [t for t, m in got[k + 1:] if isinstance(m, Status)] if k is not None else []
        require(k is not None and bool(sts), f"CONFIG: ACK then STATUS expected; got {[m for _, m in got]}")
        gaps.append((sts[0] - got[k][0]) * 1000)  # a STATUS of the old period before the ACK is no evidence
    gap = statistics.median(gaps)
    n = 9
    st = s.statuses(n, timeout_s=n * HEARTBEAT_MS / 1000 * 1.5 + s.timeout_s)
    require(len(st) >= 3, f"{len(st)} STATUS in {n * HEARTBEAT_MS * 1.5 / 1000 + s.timeout_s:.2f} s at "
                          f"heartbeat_ms={HEARTBEAT_MS}")
    # Theil-Sen: the median of the slopes between every pair of heartbeats, so one heartbeat held up
    # by the host (or the port) does not move the estimate; a chip's own clock error does
    period = theil_sen_period([t for t, _ in st]) * 1000
    tol = TIMER_TOLERANCE * HEARTBEAT_MS + s.slack_ms / 2
    require(abs(period - HEARTBEAT_MS) <= tol, f"period {period:.1f} ms over {len(st)} heartbeats "
                                               f"({HEARTBEAT_MS} ± {tol:.1f} ms)")
    low = (1 - TIMER_TOLERANCE) * HEARTBEAT_MS - s.slack_ms
    require(gap >= low, f"a CONFIG half a period after a STATUS: the next STATUS came {gap:.1f} ms after its ACK "
                        f"(median of {', '.join(f'{g:.1f}' for g in gaps)}; at least {low:.0f} ms): CONFIG did not "
                        f"restart the period")
    m = st[-1][1]
    require(m.state == ChipState.IDLE, f"state {ChipState(m.state).name}")
    require(bool(m.flags & StatusFlag.CONFIGURED), f"flags {StatusFlag(m.flags)!r}")
    require(m.flags & ~0x0F == 0, f"reserved STATUS flag bits set: 0x{m.flags:02X}")
    up = [x.uptime_s for _, x in st]
    require(up == sorted(up), f"uptime_s goes backwards: {up}")
    return f"period {period:.1f} ms over {len(st)} heartbeats; after a CONFIG the next STATUS {gap:.1f} ms later"


@check("4.11, 4.6", "CONFIG with a field out of range: NACK BAD_VALUE",
       "the chip accepts a configuration it cannot honour",
       "validate CONFIG before applying it: range > 3, filter > 3, rate_hz 0 or > 4000 -> NACK 3 BAD_VALUE")
def c_config_bad_value(s: Session):
    s.ensure_idle()
    for cfg in (Config(s.node, range=7), Config(s.node, rate_hz=0), Config(s.node, rate_hz=4001),
                Config(s.node, filter=4)):
        ans = s.request(cfg)
        require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_VALUE)], f"{cfg} answered {ans}")


@check("4.11, 4.2", "a capability the chip lacks: NACK UNSUPPORTED (CONFIG range, filter; CAL_WRITE store)",
       "the chip claims to do what it cannot, or refuses what it advertises",
       "range != 0 without MULTI_RANGE, filter != 0 without FILTER and CAL_WRITE flags bit 0 without "
       "CAL_STORAGE -> NACK 5 UNSUPPORTED; with the capability, ACK")
def c_unsupported(s: Session):
    s.ensure_idle()
    caps = int(s.info.capabilities)
    for cfg, cap in ((Config(s.node, range=1, heartbeat_ms=HEARTBEAT_MS), Capability.MULTI_RANGE),
                     (Config(s.node, filter=2, heartbeat_ms=HEARTBEAT_MS), Capability.FILTER)):
        ans = s.request(cfg)
        s.request(Config(s.node, range=0, heartbeat_ms=HEARTBEAT_MS))  # back to ±2 g whatever happened
        ok = acked(ans, s.node, MsgType.CONFIG) if caps & cap else \
            ans == [Nack(s.node, MsgType.CONFIG, NackReason.UNSUPPORTED)]
        require(ok, f"{cfg} ({'with' if caps & cap else 'without'} {cap.name}) answered {ans}")
    if not caps & Capability.CAL_STORAGE:
        ans = s.request(CalWrite(s.node, axis=0, flags=1, offset_q4=0, sensitivity=1024.0))
        require(ans == [Nack(s.node, MsgType.CAL_WRITE, NackReason.UNSUPPORTED)],
                f"CAL_WRITE store without CAL_STORAGE answered {ans}")
    return f"capabilities {Capability(caps)!r}"


@check("8.1, 4", "an undefined type outside 0x01..0x0F addressed to the node: NACK UNKNOWN_COMMAND",
       "a host cannot tell a node that lacks a command from a lost frame",
       "NACK reason 1 UNKNOWN_COMMAND, command = the type code, for an undefined type 0x00 or 0x19..0x3F "
       "addressed to the node", profiles=PROFILES)
def c_unknown(s: Session):
    s.ensure_node()
    ans = s.raw(0x3F, s.node, b"")
    require(ans == [Nack(s.node, 0x3F, NackReason.UNKNOWN_COMMAND)], f"answered {ans}")


@check("8.1, 4", "a node -> host type addressed to the chip is ignored (no NACK), defined or not",
       "on a shared bus the chip answers other nodes' frames (a NACK storm)",
       "drop every frame whose type is in 0x01..0x0F silently, whatever its node and version, and do not count it")
def c_chip_type_ignored(s: Session):
    s.ensure_idle()
    for t, payload in ((MsgType.STATUS, bytes(8)), (0x0A, b""), (MsgType.GATEWAY_INFO, bytes(8))):
        ans = s.silent(lambda: s.port.send_raw(t, s.node, payload))
        require(ans == [], f"a type 0x{t:02X} frame addressed to the chip was answered {ans}")


@check("8.1, 4.6", "a payload of the wrong length: NACK BAD_LENGTH",
       "the chip acts on truncated or padded commands",
       "compare the payload length with §4's size for the type; on a mismatch NACK 2 BAD_LENGTH")
def c_bad_length(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.START, s.node, b"\x01")
    require(ans == [Nack(s.node, MsgType.START, NackReason.BAD_LENGTH)], f"answered {ans}")


@check("12, 8.1", "a frame of another protocol version addressed to the node: NACK BAD_VERSION, in version 1",
       "a host of another version cannot learn that the node speaks v1",
       "do not decode a frame whose version is not 1; NACK 6 BAD_VERSION in the node's own version",
       profiles=PROFILES)
def c_bad_version(s: Session):
    s.ensure_node()
    ans = s.raw(MsgType.GET_INFO, s.node, b"", version=PROTOCOL_VERSION + 1)
    require(ans == [Nack(s.node, MsgType.GET_INFO, NackReason.BAD_VERSION)], f"answered {ans}")


@check("8.1, 4.9, 4.15", "a field the decoder rejects (CAL_READ axis 3, a SYNC addressed to the chip): NACK BAD_VALUE",
       "the chip reads or writes out of bounds on a bad field",
       "range-check every field on decode; NACK 3 BAD_VALUE")
def c_bad_field(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.CAL_READ, s.node, b"\x03")
    require(ans == [Nack(s.node, MsgType.CAL_READ, NackReason.BAD_VALUE)], f"CAL_READ axis 3 answered {ans}")
    ans = s.raw(MsgType.SYNC, s.node, b"\x01\x00")
    require(ans == [Nack(s.node, MsgType.SYNC, NackReason.BAD_VALUE)], f"a SYNC addressed to the chip answered {ans}")


@check("4.6, 8.1", "a broadcast is never NACKed: another version, an undefined type, a wrong length (GET_INFO)",
       "one broadcast draws a NACK from every chip of the sheet at once (a storm)",
       "answer nothing to a broadcast (node 0) that does not decode; NACK only frames addressed to you",
       profiles=PROFILES)
def c_broadcast_never_nacked(s: Session):
    s.ensure_node()
    for what, t, payload, v in (("GET_INFO of version 2", MsgType.GET_INFO, b"", PROTOCOL_VERSION + 1),
                                ("undefined type 0x3F", 0x3F, b"", None),
                                ("GET_INFO with a 1-byte payload", MsgType.GET_INFO, b"\x01", None)):
        ans = s.silent(lambda: s.port.send_raw(t, 0, payload, version=v))
        require(not [m for m in ans if isinstance(m, Nack)], f"a broadcast {what} was answered {ans}")
        require(not [m for m in ans if isinstance(m, (Ack, Announce))], f"a broadcast {what} was acted on: {ans}")


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


@check("8.5, 6.4, 6.3, 4.4", "damaged serial input is dropped silently, counted in rx_errors (not another "
       "node's frames), and the chip recovers",
       "line noise makes the chip act, hang, or go unreported",
       "drop every run that fails COBS/CRC/length without answering; count each in rx_errors (saturating), "
       "not frames for other nodes; resynchronise at the next 0x00", transport="serial")
def c_bad_input_serial(s: Session):
    s.ensure_idle()
    before = s.status().rx_errors
    body = HEADER.pack(PROTOCOL_VERSION, MsgType.GET_INFO, s.node)
    bad_crc = cobs.encode(body + ((crc16_ccitt_false(body) ^ 0x0100).to_bytes(2, "big"))) + b"\x00"
    junk = [b"\x05\x01\x02\x03\x00", bad_crc, b"\x01" * 1100 + b"\x00", b"\x03\x01\x02\x00"]
    other = s.node - 1 if s.node > 1 else s.node + 1
    foreign = encode_frame(MsgType.START, other, b"\x01")  # another node's wrong length: not counted (§8.5)
    ans = s.silent(lambda: [s.port.send_bytes(j) for j in junk + [foreign]])
    require(ans == [], f"answered damaged input with {ans}")
    ans = s.request_info(s.node)  # answered only once every byte before it was processed
    require(len(ans) == 2, f"no answer to GET_INFO after the damage: {ans}")
    after = s.status().rx_errors  # a heartbeat sent after that answer
    require(after - before == len(junk) or after == 255,
            f"rx_errors {before} -> {after}, expected +{len(junk)} (4 damaged runs; not the frame for node {other})")
    return f"rx_errors {before} -> {after}"


@check("7.1, 7.2", "frames that are not capsheet frames are not answered, and the chip recovers",
       "foreign traffic on the bus makes the chip act",
       "accept only 29-bit identifiers of version 1; ignore standard frames", transport="can")
def c_bad_input_can(s: Session):
    s.ensure_idle()
    if not isinstance(s.port.transport, CanTransport):
        raise Skip("standard-identifier frames need a CAN transport")
    ans = s.silent(lambda: s.port.transport.send_frame(0x123, b"\x01\x02", extended=False))
    require(ans == [], f"answered a standard-identifier frame with {ans}")
    ans = s.request_info(s.node)
    require(len(ans) == 2, f"no answer to GET_INFO afterwards: {ans}")


# ---------------------------------------------------------------------------------------------
# STREAMING: SYNC, SAMPLE
# ---------------------------------------------------------------------------------------------

@check("4.12, 8.3", "START: ACK, the chip is STREAMING; START again is ACKed too",
       "the chip cannot be started, or a repeated START is refused",
       "on START in IDLE: ACK and enter STREAMING; in STREAMING: ACK (idempotent)")
def c_start(s: Session):
    s.ensure_idle()
    for _ in range(2):
        ans = s.request(Start(s.node))
        require(acked(ans, s.node, MsgType.START), f"answered {ans}")
    ans = s.request_info(s.node)
    require(len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.STREAMING, f"GET_INFO: {ans}")


@check("5.1, 4.3, 4.9", "every SYNC frame -> exactly one SAMPLE with its counter, also a repeated one "
       "(within 2 ms: a SHOULD, reported)",
       "the host cannot group samples into snapshots (wrong counter, missing or duplicate answers)",
       "answer each SYNC frame with one SAMPLE carrying its counter (u16 little-endian), within 2 ms",
       level="MUST; SHOULD reported")
def c_sync(s: Session):
    s.to_streaming()
    lat = []
    counters = list(range(100, 130)) + [129]  # the last counter twice: every SYNC frame is answered (§5.1)
    for c in counters:
        c, t0, smp = s.sync_round(c)
        require(len(smp) == 1, f"SYNC 0x{c:04X}: {len(smp)} SAMPLE {[m for _, m in smp][:3]}")
        require(smp[0][1].counter == c, f"SYNC 0x{c:04X} answered with counter 0x{smp[0][1].counter:04X}")
        lat.append(smp[0][0] - t0)
    extra = [m for _, m in s.collect(s.timeout_s) if isinstance(m, Sample)]
    if s.sync_gateway is None:
        require(not extra, f"SYNCs answered twice: {len(extra)} extra SAMPLE (counters {[m.counter for m in extra][:5]})")
    med = statistics.median(lat) * 1000
    limit = SYNC_REPLY_DEADLINE_S * 1000 + s.slack_ms
    timing = (f"{len(lat)} SYNC, median {med:.2f} ms, max {max(lat) * 1000:.2f} ms (host-measured, includes the port"
              + (", and the packing gateway's collection)" if s.packing_gateway else ")"))
    return _should(s, med <= limit, f"the median SYNC->SAMPLE is over 2 ms + {s.slack_ms:g} ms slack", timing)


def _samples(s: Session, counters) -> list[Sample]:
    """One SYNC per counter (a SYNC-source gateway's own otherwise); the chip's SAMPLE answering each."""
    out = []
    for c in counters:
        c, _t0, smp = s.sync_round(c)
        match = [m for _, m in smp if m.counter == c]
        require(bool(match), f"SYNC 0x{c:04X} answered with {[m for _, m in smp] or 'nothing'}")
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


@check("5.3", "a sample sent fresh (STALE clear) is a new conversion: after a range change, the new range's counts",
       "the chip reports old conversions as fresh (a frozen or dead sensor looks alive)",
       "answer SYNC with a conversion finished since the previous SYNC, at the configured range; if there "
       "is none, repeat the last value with status STALE (bit 2). Equal fresh values are fine")
def c_stale(s: Session):
    """A frozen chip and a quiet (or noise-free) one send the same values at rest; what tells them
    apart is a conversion the frozen one cannot have done: after CONFIG range 1 every fresh sample
    is at 512 counts/g. A chip with one range gives no such handle: SKIP, not PASS."""
    if not int(s.info.capabilities) & Capability.MULTI_RANGE:
        raise Skip("the chip has one range (no MULTI_RANGE): a repeated value cannot be told from a quiet sensor")
    s.to_streaming()
    before = _samples(s, range(300, 303))
    ans = s.request(Stop(s.node))
    require(acked(ans, s.node, MsgType.STOP), f"STOP answered {ans}")
    try:
        ans = s.request(Config(s.node, rate_hz=145, range=1, filter=0, heartbeat_ms=HEARTBEAT_MS))
        require(acked(ans, s.node, MsgType.CONFIG), f"CONFIG range 1 (MULTI_RANGE) answered {ans}")
        ans = s.request(Start(s.node))
        require(acked(ans, s.node, MsgType.START), f"START answered {ans}")
        fresh, stale = None, 0
        for c in range(310, 330):
            t0 = time.monotonic()
            (m,) = _samples(s, [c])
            if not m.status & SampleStatus.STALE:
                fresh = m
                break
            stale += 1
            time.sleep(max(0.0, 1 / 145 - (time.monotonic() - t0)))  # SYNC no faster than rate_hz
    finally:
        s.request(Stop(s.node))
        s.request(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=HEARTBEAT_MS))
    if fresh is None:
        raise Skip(f"{SHOULD_NOT_MET} no fresh sample in {stale} SYNCs at 145 Hz (every one STALE; §5.3 asks "
                   f"for a conversion at rate_hz): nothing to judge")
    g = math.sqrt(fresh.x ** 2 + fresh.y ** 2 + fresh.z ** 2) / 512
    b = before[-1]
    require(0.5 <= g <= 1.5, f"after CONFIG range 1 the chip sent {(fresh.x, fresh.y, fresh.z)} unflagged: {g:.2f} g "
                             f"at 512 counts/g (before, at range 0: {(b.x, b.y, b.z)}) — a conversion it did not do")
    return f"range 0: {(b.x, b.y, b.z)}; range 1: {(fresh.x, fresh.y, fresh.z)} ({g:.2f} g), {stale} STALE first"


@check("5.1, 4.4", "missed_syncs: the 0xFFFF -> 0 wrap is no miss, a gap is counted, an older counter moves 'last'",
       "the host's lost-sample accounting is wrong",
       "add (counter − last − 1) mod 2^16 to missed_syncs when below 0x7FFF; then last = counter, whatever it "
       "was; START forgets the last counter")
def c_wraparound(s: Session):
    if s.sync_gateway is not None:
        raise Skip(f"{s.sync_gateway.label()} is the segment's SYNC source: the suite cannot choose counters")
    s.to_streaming()
    st0 = s.status().missed_syncs
    if st0 > 250:  # near saturation: start from a fresh count
        s.to_idle()
        s.to_streaming()
        st0 = s.status().missed_syncs
    s.ensure_idle()
    ans = s.request(Start(s.node))  # START forgets the last counter (§5.1)
    require(acked(ans, s.node, MsgType.START), f"START answered {ans}")
    _samples(s, (0xFFFD, 0xFFFE, 0xFFFF, 0, 1))
    st1 = s.status().missed_syncs
    require(st1 == st0, f"missed_syncs {st0} -> {st1} over a wraparound without gaps (START, 0xFFFD..0x0001)")
    _samples(s, (2, 5))  # 3 and 4 missed
    st2 = s.status().missed_syncs
    require(st2 - st1 == 2, f"missed_syncs {st1} -> {st2} after skipping 2 counters")
    _samples(s, (100, 50, 51, 53))  # 50 is older (adds nothing, last = 50); 51 follows it; 52 missed
    st3 = s.status().missed_syncs
    require(st3 - st2 == 94 + 1, f"missed_syncs {st2} -> {st3} over SYNC 5, 100, 50, 51, 53: expected +95 (94 "
                                 f"skipped before 100; 50 older, adds nothing and becomes 'last'; 52 skipped)")
    return f"missed_syncs {st0} -> {st1} -> {st2} -> {st3}"


@check("8.2, 4.10, 4.11", "CONFIG and ASSIGN while STREAMING: NACK BAD_STATE",
       "the chip changes configuration or address mid-stream",
       "refuse CONFIG, ASSIGN, CAL_WRITE while STREAMING with NACK 4 BAD_STATE (STOP first)")
def c_bad_state_streaming(s: Session):
    s.to_streaming()
    ans = s.request(Config(s.node))
    require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_STATE)], f"CONFIG answered {ans}")
    ans = s.request(Assign(s.node, new_node=s.node, link=s.link, uid_low=s.uid & 0xFFFFFFFF))
    require(ans == [Nack(s.node, MsgType.ASSIGN, NackReason.BAD_STATE)], f"ASSIGN answered {ans}")


@check("4.12", "STOP: ACK, back to IDLE, SYNC no longer answered; STOP again is ACKed",
       "the chip cannot be stopped and keeps loading the bus",
       "on STOP in STREAMING: ACK and enter IDLE; in IDLE: ACK")
def c_stop(s: Session):
    s.to_streaming()
    for _ in range(2):
        ans = s.request(Stop(s.node))
        require(acked(ans, s.node, MsgType.STOP), f"answered {ans}")
    if s.sync_gateway is None:
        ans = s.silent(Sync(counter=7))
    else:  # the gateway's next SYNC: nothing for it from the chip
        got = s.collect(s.gateway_sync_wait_s, lambda ms: sum(isinstance(m, Sync) for m in ms) >= 2, syncs=True)
        ans = [m for _, m in got if isinstance(m, Sample)]
    require(ans == [], f"SYNC after STOP answered {ans}")


@check("4.4", "uptime_s counts from power-on: RESET does not restart it",
       "a host cannot tell a protocol RESET from a real reboot (a brown-out) by uptime going backwards",
       "keep the uptime counter across RESET; restart it only at power-on")
def c_uptime(s: Session):
    s.ensure_idle()
    u1 = s.status().uptime_s
    deadline = time.monotonic() + 3.0
    while u1 < 2 and time.monotonic() < deadline:  # a chip (re)started under a second ago: wait for evidence
        u1 = s.status().uptime_s
    require(u1 >= 2, f"uptime_s {u1} after 3 s more of STATUS: it does not count seconds")
    s.to_idle()  # RESET, ASSIGN, CONFIG
    u2 = s.status().uptime_s
    require(u2 >= u1, f"uptime_s {u1} before a RESET, {u2} after it: RESET restarted it")
    return f"uptime_s {u1} -> {u2} across a RESET"


# ---------------------------------------------------------------------------------------------
# Broadcast that changes state (only with --allow-broadcast: they address every chip on the port)
# ---------------------------------------------------------------------------------------------

@check("4.6, 8.2", "a broadcast refused by the state table or by CONFIG's checks gets no NACK and changes nothing",
       "one broadcast causes a NACK from every chip (a storm), or applies half a configuration",
       "for a broadcast (node 0) frame, refuse silently: never NACK a broadcast", broadcast=True)
def c_broadcast_silent(s: Session):
    s.fresh_boot()
    ans = s.silent(Start(0))
    require(ans == [], f"START broadcast in BOOT answered {ans}")
    s.to_idle()
    ans = s.silent(Config(0, rate_hz=5000, heartbeat_ms=HEARTBEAT_MS))
    require(ans == [], f"a broadcast CONFIG with rate_hz 5000 answered {ans}")


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
# Gateways (--profile gateway, docs/protocol.md §13)
# ---------------------------------------------------------------------------------------------

@check("13.1, 4.13", "GET_INFO (broadcast) is answered with ANNOUNCE, INFO (GATEWAY), GATEWAY_INFO",
       "the host cannot find the gateway, so it cannot learn that it packs or drives SYNC",
       "be a node: answer GET_INFO with ANNOUNCE, INFO with capability bit 6 GATEWAY, then one GATEWAY_INFO "
       "per run of links", profiles=("gateway",))
def c_gateway_discover(s: Session):
    detail = _discover(s, "gateway")
    got = s.request(GetInfo(s.cur), 3, keep=(Announce, Info, GatewayInfo))
    require(len(got) >= 3 and isinstance(got[2], GatewayInfo) and got[2].node == s.cur,
            f"GET_INFO to the gateway answered {got}: INFO is followed by GATEWAY_INFO (§13.1)")
    return detail


@check("4.16, 4.2", "INFO and GATEWAY_INFO agree: capabilities for what it does, runs in range, a rate iff a SYNC source",
       "the host learns the wrong thing: packing it cannot do, links that do not exist, a SYNC rate of 0",
       "set PACKING only with capability SNAPSHOT and SYNC_SOURCE only with capability SYNC_SOURCE; "
       "sync_rate_hz > 0 exactly when flag SYNC_SOURCE; adc_bits 0; reserved bits 0; runs ascending, "
       "not overlapping", profiles=("gateway",))
def c_gateway_info(s: Session):
    s.need_chip()
    i = s.info
    g = s.gateways.get(s.uid)
    require(g is not None and g.runs, "no GATEWAY_INFO heard from the gateway")
    caps = int(i.capabilities)
    require(i.protocol_version == PROTOCOL_VERSION and i.adc_bits == 0,
            f"INFO protocol_version {i.protocol_version}, adc_bits {i.adc_bits} (a gateway: 1 and 0)")
    require(caps & RESERVED_CAPABILITIES == 0, f"reserved capability bits set: 0x{caps:04X}")
    runs = sorted(g.runs.values(), key=lambda r: r.first_link)
    for r in runs:
        require(int(r.flags) & ~0x03 == 0, f"reserved GATEWAY_INFO flag bits: {r}")
        require(r.sample_format in SampleFormat._value2member_map_,
                f"sample_format {r.sample_format} (0 SAMPLE words; since 1.2 also 1 and 2, IMU records, §16.5)")
        require(not r.flags & GatewayFlag.PACKING or caps & Capability.SNAPSHOT,
                f"flag PACKING without capability SNAPSHOT: {r}")
        require(not r.flags & GatewayFlag.SYNC_SOURCE or caps & Capability.SYNC_SOURCE,
                f"flag SYNC_SOURCE without capability SYNC_SOURCE: {r}")
        require(bool(r.flags & GatewayFlag.SYNC_SOURCE) == (r.sync_rate_hz > 0),
                f"sync_rate_hz {r.sync_rate_hz} with flag SYNC_SOURCE {'set' if r.flags & GatewayFlag.SYNC_SOURCE else 'clear'}")
    for a, b in zip(runs, runs[1:]):
        require(a.first_link + a.link_count <= b.first_link, f"runs overlap: {a} and {b}")
    return f"flags {g.flags!r}, runs {[(r.first_link, r.link_count) for r in runs]}, capabilities {Capability(caps)!r}"


@check("13.1, 4.6", "a chip command addressed to the gateway: NACK UNSUPPORTED",
       "a host cannot tell a gateway from a chip that ignores it",
       "answer CONFIG, START, STOP, CAL_WRITE and CAL_READ addressed to the gateway with NACK 5 UNSUPPORTED",
       profiles=("gateway",))
def c_gateway_unsupported(s: Session):
    s.assign_gateway()
    for msg in (Config(s.node), Start(s.node), CalRead(s.node, axis=0)):
        ans = s.request(msg)
        require(ans == [Nack(s.node, msg.TYPE, NackReason.UNSUPPORTED)], f"{msg} answered {ans}")


@check("13.1, 14", "an assigned gateway sends STATUS every 1 s (± 5 %), IDLE",
       "the host cannot tell a live gateway from a dead one",
       "once assigned, send STATUS every 1000 ms from a free-running time base", profiles=("gateway",))
def c_gateway_status(s: Session):
    s.assign_gateway()
    s.drain()
    st = s.statuses(4, timeout_s=4 * GATEWAY_HEARTBEAT_MS / 1000 * 1.3 + s.timeout_s)
    require(len(st) >= 3, f"{len(st)} STATUS in {4 * GATEWAY_HEARTBEAT_MS * 1.3 / 1000 + s.timeout_s:.1f} s")
    period = theil_sen_period([t for t, _ in st]) * 1000
    tol = TIMER_TOLERANCE * GATEWAY_HEARTBEAT_MS + s.slack_ms
    require(abs(period - GATEWAY_HEARTBEAT_MS) <= tol, f"period {period:.0f} ms ({GATEWAY_HEARTBEAT_MS} ± {tol:.0f})")
    require(st[-1][1].state == ChipState.IDLE, f"state {st[-1][1].state!r}")
    return f"period {period:.0f} ms over {len(st)} STATUS"


@check("13.3, 5.1", "a SYNC source: its SYNC at sync_rate_hz (± 5 %), counters + 1; the host's SYNC is not passed on",
       "the chips answer two SYNC sources: every counter of one is a gap in the other's (missed_syncs saturates)",
       "generate SYNC at the rate GATEWAY_INFO says, forward each to the host; drop SYNC from the host and "
       "count it in STATUS missed_syncs", profiles=("gateway",))
def c_gateway_sync_source(s: Session):
    s.assign_gateway()
    g = s.gateways[s.uid]
    if not g.flags & GatewayFlag.SYNC_SOURCE:
        raise Skip("the gateway is not a SYNC source (GATEWAY_INFO flag SYNC_SOURCE clear)")
    rate = g.sync_rate_hz
    before = s.status().missed_syncs
    s.drain()
    host = [0x7A00 + k for k in range(5)]
    for c in host:
        s.port.send(Sync(counter=c))
    got = s.collect(max(1.0, 20 / rate) + s.timeout_s, lambda ms: sum(isinstance(m, Sync) for m in ms) >= 20,
                    syncs=True)
    syn = [(t, m) for t, m in got if isinstance(m, Sync)]
    require(len(syn) >= 5, f"{len(syn)} SYNC from the gateway in {max(1.0, 20 / rate) + s.timeout_s:.1f} s at "
                           f"sync_rate_hz {rate}")
    ctr = [m.counter for _, m in syn]
    require(all((b - a) & 0xFFFF == 1 for a, b in zip(ctr, ctr[1:])), f"its counters do not step by 1: {ctr[:8]}")
    require(not set(ctr) & set(host), "the host's SYNC came back through the gateway")
    per = (syn[-1][0] - syn[0][0]) / (len(syn) - 1)
    tol = TIMER_TOLERANCE / rate + s.slack_ms / 1000
    require(abs(per - 1 / rate) <= tol, f"SYNC period {per * 1000:.2f} ms (1/{rate} Hz ± {tol * 1000:.1f} ms)")
    after = s.status().missed_syncs
    require(after - before == len(host) or after == 255,
            f"STATUS missed_syncs {before} -> {after}: the {len(host)} host SYNCs it refused are counted there")
    return f"{len(syn)} SYNC, period {per * 1000:.2f} ms; {len(host)} host SYNC refused and counted"


def _a_chip_behind(s: Session):
    """Assign and start the first chip heard behind the gateway (for a packing check): its uid, node, link."""
    chips = [u for u, k in s.uids_heard.items() if k == "chip"]
    if not chips:
        raise Skip("no chip answered behind the gateway: a SYNC nobody answers is answered by nothing (§13.2)")
    g = s.gateways[s.uid]
    link = g.first_link()
    if link is None:
        raise Skip("the gateway announced no links")
    uid = chips[0]
    node = s.node_of_uid[uid]
    chip_node = s.node - 1
    s.drain()
    s.port.send(Assign(node, new_node=chip_node, link=link, uid_low=uid & 0xFFFFFFFF))
    s.port.send(Start(chip_node))
    s.collect(s.timeout_s)
    return uid, chip_node, link


@check("13.2, 4.8", "packing: every SYNC a chip answered -> SNAPSHOT frames with every link of the runs once, "
       "in order, from the gateway; links not heard INVALID",
       "the host loses links, reads a chip's sample on another link, or takes silence for data",
       "answer SYNC with SNAPSHOT frames covering each GATEWAY_INFO run exactly once, ascending, at most 202 "
       "(serial) or 11 (CAN FD) samples each, from your node id; INVALID with counts 0 for links whose SAMPLE "
       "did not arrive by 10 ms after the SYNC", profiles=("gateway",))
def c_gateway_packing(s: Session):
    s.assign_gateway()
    g = s.gateways[s.uid]
    if not g.flags & GatewayFlag.PACKING:
        raise Skip("the gateway does not pack (GATEWAY_INFO flag PACKING clear)")
    fmts = _packed_formats(g)
    if fmts - {SampleFormat.ACCEL_12}:
        raise Skip(f"the gateway packs IMU records (GATEWAY_INFO sample_format {sorted(fmts)}): check of §16.5")
    uid, chip_node, link = _a_chip_behind(s)
    runs = sorted((r.first_link, r.link_count) for r in g.runs.values() if r.link_count)
    cap = 202 if s.port.kind == "serial" else 11
    try:
        for c in range(40, 43):
            s.drain()
            if not g.flags & GatewayFlag.SYNC_SOURCE:
                s.port.send(Sync(counter=c))
            got = []
            deadline = time.monotonic() + s.answer_s
            want = sum(n for _, n in runs)
            while time.monotonic() < deadline:
                item = s.port.next(deadline)
                if item is None:
                    break
                s.note(*item)
                if isinstance(item[1], Snapshot) and item[1].node == s.node:
                    got.append(item[1])
                    if sum(x.count for x in got if x.counter == got[0].counter) >= want:
                        break
            require(bool(got), f"SYNC 0x{c:04X} (the chip on link {link} streams) answered with no SNAPSHOT "
                               f"from the gateway's node 0x{s.node:04X}")
            c0 = got[0].counter
            frames = [x for x in got if x.counter == c0]
            covered = [(x.first_link, x.count) for x in frames]
            require(all(n <= cap for _, n in covered), f"a SNAPSHOT over {cap} samples: {covered}")
            links = [x.first_link + k for x in frames for k in range(x.count)]
            want_links = [a + k for a, n in runs for k in range(n)]
            require(links == want_links, f"SNAPSHOT frames of counter 0x{c0:04X} cover links "
                                         f"{covered}, the runs are {runs} (each link once, ascending)")
            for x in frames:
                for k in range(x.count):
                    ln = x.first_link + k
                    st, cnt = int(x.status[k]), x.counts[k].tolist()
                    if ln == link:
                        require(not st & SampleStatus.INVALID, f"the streaming chip's link {ln} is INVALID")
                    else:
                        require(st & SampleStatus.INVALID and cnt == [0, 0, 0],
                                f"link {ln} (no chip streams there) is {cnt} status 0x{st:X}, not INVALID with counts 0")
    finally:
        s.port.send(Stop(chip_node))
        s.port.send(Reset(chip_node))
        s.collect(s.timeout_s)
    return f"runs {runs}: every link once per counter; the chip on link {link} valid, the rest INVALID"


def _packed_formats(g) -> set:
    """The sample formats a gateway's runs pack (GATEWAY_INFO ``sample_format``, §4.16, §16.5)."""
    return {int(r.sample_format) for r in g.runs.values() if r.link_count}


# ---------------------------------------------------------------------------------------------
# Everything the node sent during the run
# ---------------------------------------------------------------------------------------------

@check("6.2, 6.1, 6.3, 7.1, 7.2, 4.8", "every frame from the node decoded (COBS, CRC / identifier, priority, "
       "lengths); no SNAPSHOT from a chip",
       "a host drops the node's frames (wrong CRC variant, framing, identifier layout or priority)",
       "CRC-16/CCITT-FALSE (check 0x29B1) over header + payload, MSB first, then COBS and 0x00; on CAN "
       "the §4 priority in bits 28..26 and classic frames for payloads ≤ 8 bytes", profiles=PROFILES,
       needs_node=False)
def c_framing(s: Session):
    """Runs also when no node was found: frames that arrive damaged, all of them, are a node's framing."""
    p = s.port
    if p.frames == 0 and p.damaged == 0:
        raise Skip("nothing received")
    if s.cur is None and not p.damaged:
        raise Skip("no node found, and nothing damaged arrived")
    chip = s.systematic_damage()
    if chip:
        raise CheckFailed(chip)
    if p.damaged and not p.lossy:
        raise CheckFailed(f"{p.damaged} of {p.damaged + p.frames} frames did not decode "
                          f"({dict(p.damage)}): the node's framing, not the port")
    bad = p.bad_ids  # the port's FrameAudit: §7.1 identifiers of every CAN frame received
    require(not bad, "; ".join(bad[:3]))
    if s.profile == "chip":
        require(not s.by_type.get((int(MsgType.SNAPSHOT), True)), "a chip sent SNAPSHOT (§4.8: gateways only)")
    if p.damaged:
        raise PortLost(f"{p.damaged} of {p.damaged + p.frames} frames did not decode ({dict(p.damage)})")
    mine = sum(v for (t, ok), v in s.by_type.items() if ok)
    return f"{mine} frames from the node, {p.frames} in all"


def _from(s: Session, raw: bytes) -> bool:
    """The serial frame came from a node id the node under test used (header intact)."""
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


@check("2, 4.5, 4.2, 4.4", "every frame is byte-identical to the reference encoding of its fields "
       "(reserved bits 0, little-endian)",
       "the node sends non-zero reserved bits or a non-canonical encoding; a future version may give them meaning",
       "send reserved bits and bytes as 0 (ACK detail, flags, capabilities); encode as the golden vectors (§9)",
       profiles=PROFILES)
def c_canonical(s: Session):
    s.need_chip()
    bad, n = [], 0
    if s.port.kind == "serial":
        for raw in list(s.port.raw):
            if not _from(s, raw):
                continue
            if isinstance(decode_frame(raw.rstrip(b"\x00")), DecodeError):
                continue
            n += 1
            d = _canonical_serial(raw)
            if d:
                bad.append(d)
    else:  # CAN: the port's FrameAudit keeps every extended data frame received
        from protocol.can import to_can
        for aid, data, fd in list(s.port.raw):
            msg = decode_can(aid, data, is_fd=fd)
            if isinstance(msg, DecodeError) or not isinstance(msg, Message) or msg.node not in s.my_nodes:
                continue
            n += 1
            ref = to_can(msg, fd=fd)
            if ref.data != data or (ref.arbitration_id & 0x03FFFFFF) != (aid & 0x03FFFFFF):
                bad.append(f"{msg.TYPE.name}: sent {aid:08X}#{data.hex()}, reference "
                           f"{ref.arbitration_id:08X}#{ref.data.hex()}")
    if n == 0:
        raise Skip("no frame of the node was recorded: nothing to compare")
    require(not bad, f"{len(bad)} of {n} frames differ from the reference encoding; first: {bad[0] if bad else ''}")
    acks = [m for m in s.acks if m.detail != 0]
    require(not acks, f"{len(acks)} ACK with detail != 0 (reserved in 1.1), first: {acks[:1]}")
    return f"{n} frames compared"


@check("7.3", "every frame from the node decodes with the DBC (cantools) to the same fields",
       "CAN tools using protocol/capsheet.dbc misread the node",
       "use the §7.1 identifiers and §4 layouts (the DBC is generated from them)", transport="can",
       profiles=PROFILES)
def c_dbc(s: Session):
    s.need_chip()
    from protocol.dbc import load_database
    db = load_database()
    bad, n = [], 0
    for aid, data, fd in list(s.port.raw):  # CAN: (arbitration_id, data, is_fd) of every frame received
        msg = decode_can(aid, data, is_fd=fd)
        if not isinstance(msg, (Sample, Ack, Nack, Status, Announce, Info, GatewayInfo)) or msg.node not in s.my_nodes:
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
    if n == 0:
        raise Skip("no frame of the node was recorded: nothing to decode")
    require(not bad, f"{len(bad)} of {n} frames: {bad[0] if bad else ''}")
    return f"{n} frames decoded by the DBC"


# ---------------------------------------------------------------------------------------------
# 6/9-axis chips (v1.2, §16): only on a chip whose INFO has GYRO
# ---------------------------------------------------------------------------------------------

def _imu_caps(s: Session) -> Capability:
    s.need_chip()
    caps = Capability(s.info.capabilities) if s.info is not None else Capability.NONE
    if not caps & Capability.GYRO:
        raise Skip("the chip's INFO has no GYRO capability: an accelerometer chip, §16 does not apply")
    return caps


def _config_imu(s: Session, fmt: int, gyro: int = 3, mag: int = 0, flags: int = 0) -> list:
    return s.request(ConfigImu(s.node, fmt, gyro, mag, flags))


def _nacked(ans, s: Session, reason: NackReason) -> bool:
    return any(isinstance(m, Nack) and m.node == s.node and m.command == MsgType.CONFIG_IMU and m.reason == reason
               for m in ans)


@check("16.2, 4.6, 8.2", "CONFIG_IMU: values out of range NACK BAD_VALUE, a sensor or CAN FD the chip lacks "
       "NACK UNSUPPORTED, refused while STREAMING (BAD_STATE), accepted in IDLE",
       "a host cannot select the 6/9-axis records, or selects one the chip cannot send",
       "check CONFIG_IMU's fields in §16.2's order before changing anything; ACK it in IDLE and FAULT")
def c_config_imu(s: Session):
    caps = _imu_caps(s)
    s.ensure_idle()
    for cfg in ((3, 3, 0), (1, 5, 0), (1, 3, 4)):
        ans = _config_imu(s, *cfg)
        require(_nacked(ans, s, NackReason.BAD_VALUE), f"CONFIG_IMU format/gyro/mag {cfg} answered {ans}")
    lacks = []
    if not caps & Capability.MAG:
        lacks.append(((2, 3, 0, 0), "format 2 without MAG"))
    if not caps & Capability.CAN_FD:
        lacks.append(((1, 3, 0, int(ConfigImuFlag.FD)), "flag FD without CAN_FD"))
    for cfg, why in lacks:
        ans = _config_imu(s, *cfg)
        require(_nacked(ans, s, NackReason.UNSUPPORTED), f"CONFIG_IMU {why} answered {ans}")
    fmt = 2 if caps & Capability.MAG else 1
    ans = _config_imu(s, fmt)
    require(acked(ans, s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} in IDLE answered {ans}")
    s.to_streaming()
    ans = _config_imu(s, 0)
    require(_nacked(ans, s, NackReason.BAD_STATE), f"CONFIG_IMU while STREAMING answered {ans}")
    require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
    ans = _config_imu(s, 0)
    require(acked(ans, s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format 0 in IDLE answered {ans}")
    return f"format {fmt} taken, {3 + len(lacks)} refusals as §16.2 orders them, BAD_STATE while STREAMING"


def _imu_round(s: Session, c: int) -> list:
    """SYNC ``c``: every answer of the chip to it, ``[(time, msg)]`` (records, and SAMPLEs that should not be)."""
    s.drain()
    s.port.send(Sync(counter=c))
    got = s.collect(s.answer_s, lambda ms: any(isinstance(m, (ImuSample, Sample)) and m.counter == c for m in ms))
    got += s.collect(min(0.05, s.timeout_s))  # a second answer to the same SYNC, if the chip sends one
    return [(t, m) for t, m in got if isinstance(m, (ImuSample, Sample))]


@check("16.3, 16.1, 5.1", "in format 1 or 2: every SYNC -> exactly one IMU record of that format with its counter; "
       "SATURATED exactly at the rails of every count; time_us −32768 iff the chip lacks SAMPLE_TIME, else within "
       "a SYNC period of the SYNC",
       "a host gets no gyroscope (or magnetometer), the wrong record, or sample times it cannot integrate with",
       "answer each SYNC with one IMU_SAMPLE (classic CAN: §16.4's frames) of the configured format; set "
       "SATURATED from the counts sent; send time_us (µs after the SYNC) or −32768 without SAMPLE_TIME")
def c_imu_records(s: Session):
    caps = _imu_caps(s)
    if s.sync_gateway is not None or s.packing_gateway:
        raise Skip("behind a gateway that drives SYNC or packs: the records are the gateway's business (§16.5)")
    s.ensure_idle()
    fmt = 2 if caps & Capability.MAG else 1
    require(acked(_config_imu(s, fmt), s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} refused")
    s.to_streaming()
    timed = bool(caps & Capability.SAMPLE_TIME)
    seen = []
    for c in range(300, 316):
        ans = _imu_round(s, c)
        mine = [m for _, m in ans if m.counter == c]
        require(len(mine) == 1 and isinstance(mine[0], ImuSample),
                f"SYNC 0x{c:04X} answered {[m for _, m in ans][:3]} (one IMU record of format {fmt})")
        m = mine[0]
        require(m.format == fmt, f"SYNC 0x{c:04X}: a format-{int(m.format)} record after CONFIG_IMU format {fmt}")
        counts = (m.x, m.y, m.z)
        rails = any(v in (-2048, 2047) for v in counts) or any(v in (-32768, 32767) for v in m.gyro + (m.mag or ()))
        require(rails == bool(m.status & SampleStatus.SATURATED),
                f"SATURATED {'clear' if rails else 'set'} for accel {counts}, gyro {m.gyro}, mag {m.mag}")
        if timed:
            require(m.time_us != TIME_UNKNOWN, f"time_us unknown (−32768) from a chip with SAMPLE_TIME (§16.1)")
            require(abs(m.time_us) <= 1e6 / 145 + 2000,
                    f"time_us {m.time_us} µs: more than a SYNC period (145 Hz) from its SYNC")
        else:
            require(m.time_us == TIME_UNKNOWN, f"time_us {m.time_us} from a chip without SAMPLE_TIME: −32768 (§16.1)")
        seen.append(m)
    require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
    require(acked(_config_imu(s, 0), s.node, MsgType.CONFIG_IMU), "CONFIG_IMU format 0 refused")
    last = seen[-1]
    return (f"{len(seen)} records of format {fmt}; last accel {(last.x, last.y, last.z)}, gyro {last.gyro}"
            + (f", mag {last.mag}" if last.mag else "") + f", time_us {last.time_us}")


@check("16.4, 7.2", "classic CAN: a record as IMU_GYRO (IMU_MAG) IMU_ACCEL, in that order, back to back, "
       "each 8 bytes, one counter", "a receiver cannot assemble the records (it reports them incomplete)",
       "send the frames of §16.4 in their order with the record's counter (IMU_ACCEL: its low byte)",
       transport="can")
def c_imu_can_frames(s: Session):
    caps = _imu_caps(s)
    if s.sync_gateway is not None or s.packing_gateway:
        raise Skip("behind a gateway that drives SYNC or packs (§16.5)")
    fmt = 2 if caps & Capability.MAG else 1
    s.ensure_idle()
    require(acked(_config_imu(s, fmt), s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} refused")
    s.to_streaming()
    s.port.raw.clear()
    for c in range(400, 408):
        _imu_round(s, c)
    require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
    require(acked(_config_imu(s, 0), s.node, MsgType.CONFIG_IMU), "CONFIG_IMU format 0 refused")
    want = [MsgType.IMU_GYRO] + ([MsgType.IMU_MAG] if fmt == 2 else []) + [MsgType.IMU_ACCEL]
    seq = [(t, aid, d) for aid, d, _fd in s.port.raw for t in [(aid >> 20) & 0x3F]
           if (aid & 0xFFFF) == s.node and t in (MsgType.IMU_GYRO, MsgType.IMU_MAG, MsgType.IMU_ACCEL, MsgType.IMU_SAMPLE)]
    require(bool(seq), "no IMU frame from the chip")
    types = [t for t, _, _ in seq]
    require(len(types) % len(want) == 0 and all(types[i:i + len(want)] == want for i in range(0, len(types), len(want))),
            f"frame types {[MsgType(t).name for t in types[:6]]}: §16.4 sends {[w.name for w in want]} per record")
    for i in range(0, len(seq), len(want)):
        grp = seq[i:i + len(want)]
        require(all(len(d) == 8 for _, _, d in grp), f"IMU frames of {[len(d) for _, _, d in grp]} bytes, not 8")
        ctr = grp[0][2][0] | grp[0][2][1] << 8
        require(all((d[0] | d[1] << 8) == ctr for _, _, d in grp[1:-1]) and grp[-1][2][0] == ctr & 0xFF,
                f"a record's frames carry different counters: {[d.hex() for _, _, d in grp]}")
    return f"{len(seq) // len(want)} records, {len(want)} frames each, in order"


def _cal_imu_nack(ans, s: Session, t: MsgType) -> bool:
    return ans == [Nack(s.node, t, NackReason.UNSUPPORTED)]


def _cal_imu_value(block: int, index: int) -> float:
    """A distinct float32 per element for check 45: a −0, a subnormal, large and small magnitudes."""
    if (block, index) == (CalBlock.GYRO_G_SENS, 4):
        return -0.0
    if (block, index) == (CalBlock.MAG_HARD_IRON, 2):
        return 1e-40  # subnormal in binary32
    return float(struct.unpack("<f", struct.pack("<f", (-1) ** index * (block + 1) * (index + 3) * 1.25e-3))[0])


@check("17.2, 17.1, 17.3", "CAL_IMU_WRITE then CAL_IMU_READ gives every gyroscope (and magnetometer) calibration "
       "element back bit for bit with its stored flag, and the chip applies it (a zero matrix sends zero counts); "
       "a chip without the sensor answers both with NACK 5 UNSUPPORTED (a chip answering both NACK 1, one of 1.2 or "
       "earlier, is skipped)",
       "a host cannot store the gyroscope's or magnetometer's calibration on the chip, or gets another back",
       "keep the CAL_IMU_WRITE value per element as given (binary32, −0 and subnormals included), answer "
       "CAL_IMU_READ with CAL_IMU_DATA carrying it; apply §17.3 to the counts sent; NACK 5 for a block whose "
       "sensor the chip lacks")
def c_cal_imu(s: Session):
    s.need_chip()
    caps = Capability(s.info.capabilities) if s.info is not None else Capability.NONE
    s.ensure_idle()
    have = [b for b in CalBlock if caps & (Capability.GYRO if b <= CalBlock.GYRO_G_SENS else Capability.MAG)]
    lacks = [b for b in (CalBlock.GYRO_BIAS, CalBlock.MAG_MATRIX) if b not in have]
    # §17.2, §12: a chip of 1.2 or earlier does not know the types (NACK 1, §8.1), and the wire carries no
    # minor version to tell it from a 1.3 chip: both types NACK 1 is such a chip, to which §17 does not apply
    probe = (have or lacks)[0]
    ans = s.request(CalImuRead(s.node, probe, 0))
    if ans == [Nack(s.node, MsgType.CAL_IMU_READ, NackReason.UNKNOWN_COMMAND)]:
        ans = s.request(CalImuWrite(s.node, probe, 0, 0, 0, cal_block_nominal(probe, 0)))  # nominal: changes nothing
        require(ans == [Nack(s.node, MsgType.CAL_IMU_WRITE, NackReason.UNKNOWN_COMMAND)],
                f"CAL_IMU_READ answered NACK 1 UNKNOWN_COMMAND (a chip of 1.2 or earlier) but CAL_IMU_WRITE {ans} "
                f"(§17.2, §8.1: a chip knows both types or neither)")
        raise Skip("CAL_IMU_READ and CAL_IMU_WRITE answered NACK 1 UNKNOWN_COMMAND: a chip of protocol 1.2 or "
                   "earlier, which does not know them (§17.2, §12); §17 does not apply")
    for b in lacks:
        ans = s.request(CalImuRead(s.node, b, 0))
        require(_cal_imu_nack(ans, s, MsgType.CAL_IMU_READ), f"CAL_IMU_READ block {int(b)} without its sensor "
                                                               f"answered {ans} (§17.2: NACK 5)")
        ans = s.request(CalImuWrite(s.node, b, 0, 0, 0, 0.5))
        require(_cal_imu_nack(ans, s, MsgType.CAL_IMU_WRITE), f"CAL_IMU_WRITE block {int(b)} without its sensor "
                                                                f"answered {ans} (§17.2: NACK 5)")
    if not have:
        return "no gyroscope, no magnetometer: CAL_IMU_READ and CAL_IMU_WRITE answered NACK 5"
    elements = [(b, i) for b in have for i in range(CAL_BLOCK_SIZE[b])]
    try:
        for b, i in elements:
            ans = s.request(CalImuWrite(s.node, b, i, 0, 0, _cal_imu_value(b, i)))
            require(acked(ans, s.node, MsgType.CAL_IMU_WRITE), f"CAL_IMU_WRITE block {int(b)} index {i} answered {ans}")
        for b, i in elements:
            ans = s.request(CalImuRead(s.node, b, i))
            want = struct.pack("<f", _cal_imu_value(b, i))
            require(len(ans) == 1 and isinstance(ans[0], CalImuData) and (ans[0].block, ans[0].index) == (b, i)
                    and ans[0].flags & 1 == 0 and struct.pack("<f", ans[0].value) == want,
                    f"CAL_IMU_READ block {int(b)} index {i} answered {ans} (written: {want.hex()}, not stored)")
        applied = "not checked behind a gateway that drives SYNC or packs"
        if s.sync_gateway is None and not s.packing_gateway:
            for b in have:  # zero matrices: every gyroscope (and magnetometer) count sent is 0 (§17.3)
                if b in (CalBlock.GYRO_MATRIX, CalBlock.MAG_MATRIX):
                    for i in range(9):
                        require(acked(s.request(CalImuWrite(s.node, b, i, 0, 0, 0.0)), s.node, MsgType.CAL_IMU_WRITE),
                                "CAL_IMU_WRITE refused")
            fmt = 2 if caps & Capability.MAG else 1
            require(acked(_config_imu(s, fmt), s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} refused")
            s.to_streaming()
            recs = []
            for c in range(500, 504):
                recs += [m for _, m in _imu_round(s, c) if isinstance(m, ImuSample) and m.counter == c]
            require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
            require(acked(_config_imu(s, 0), s.node, MsgType.CONFIG_IMU), "CONFIG_IMU format 0 refused")
            require(len(recs) == 4, f"{len(recs)} IMU records for 4 SYNCs")
            bad = [m for m in recs if m.gyro != (0, 0, 0) or (fmt == 2 and m.mag != (0, 0, 0))]
            require(not bad, f"with zero matrices the chip sent gyro {bad[0].gyro if bad else ''}"
                             f"{', mag ' + str(bad[0].mag) if bad and fmt == 2 else ''} (§17.3: 0)")
            applied = "zero matrices applied (4 records of zeros)"
    finally:  # leave the chip as it was: every element nominal, not stored
        s.ensure_idle()
        for b, i in elements:
            s.request(CalImuWrite(s.node, b, i, 0, 0, cal_block_nominal(b, i)))
    return (f"{len(elements)} elements read back bit for bit; {applied}"
            + (f"; blocks {[int(b) for b in lacks]} without their sensor: NACK 5" if lacks else ""))


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
    fn = c_gateway_discover if profile == "gateway" else c_discover
    return next(c for c in CHECKS if c.fn is fn)


@check("16.5, 13.2, 13.1, 16.1", "packing IMU records (sample_format 1 or 2): every SYNC a chip answered -> "
       "SNAPSHOT_IMU frames of that format with every link of the runs once, in order, from the gateway; links "
       "not heard INVALID records; the chip's own records not passed on",
       "the host loses a 6/9-axis sheet's links or reads them in the wrong format: the gateway did not configure "
       "its chips, packed the wrong record size, or passed records on beside its SNAPSHOT_IMU",
       "configure your chips to the GATEWAY_INFO sample_format (CONFIG_IMU) before passing START on; answer SYNC "
       "with SNAPSHOT_IMU frames of that format covering each run once, ascending, at most 77/53 (serial) or 4/3 "
       "(CAN FD) records each; a link not heard by 10 ms: INVALID, counts 0, time_us -32768; pass no record "
       "of a covered link on", profiles=("gateway",))
def c_gateway_packing_imu(s: Session):
    from protocol.can import MAX_FD_IMU_RECORDS
    from protocol.messages import MAX_SERIAL_IMU_RECORDS, ImuAccel, ImuGyro, ImuMag, SnapshotImu
    s.assign_gateway()
    g = s.gateways[s.uid]
    if not g.flags & GatewayFlag.PACKING:
        raise Skip("the gateway does not pack (GATEWAY_INFO flag PACKING clear)")
    fmts = _packed_formats(g)
    if fmts <= {SampleFormat.ACCEL_12}:
        raise Skip("the gateway packs SAMPLEs (GATEWAY_INFO sample_format 0): check 38's")
    require(len(fmts) == 1 and fmts <= {1, 2}, f"GATEWAY_INFO sample_format {sorted(fmts)}: one of 1, 2 (§16.5)")
    fmt = SampleFormat(fmts.pop())
    uid, chip_node, link = _a_chip_behind(s)
    runs = sorted((r.first_link, r.link_count) for r in g.runs.values() if r.link_count)
    cap = (MAX_SERIAL_IMU_RECORDS if s.port.kind == "serial" else MAX_FD_IMU_RECORDS)[fmt]
    want_links = [a + k for a, n in runs for k in range(n)]
    unpacked = (Sample, ImuSample, ImuGyro, ImuMag, ImuAccel)
    try:
        for c in range(40, 43):
            s.drain()
            if not g.flags & GatewayFlag.SYNC_SOURCE:
                s.port.send(Sync(counter=c))
            got, passed = [], []
            deadline = time.monotonic() + s.answer_s
            while time.monotonic() < deadline:
                item = s.port.next(deadline)
                if item is None:
                    break
                s.note(*item)
                m = item[1]
                if isinstance(m, SnapshotImu) and m.node == s.node:
                    got.append(m)
                    if sum(x.count for x in got if x.counter == got[0].counter) >= len(want_links):
                        break
                elif isinstance(m, unpacked) and m.node == chip_node:
                    passed.append(m)
            require(bool(got), f"§16.5: SYNC 0x{c:04X} (the chip on link {link} streams) answered with no "
                               f"SNAPSHOT_IMU from the gateway's node 0x{s.node:04X}"
                               + (f"; the chip's {type(passed[0]).__name__} was passed on" if passed else ""))
            c0 = got[0].counter
            frames = [x for x in got if x.counter == c0]
            require(all(x.format == fmt for x in frames),
                    f"§16.5: SNAPSHOT_IMU of format {sorted({int(x.format) for x in frames})}, GATEWAY_INFO says {int(fmt)}")
            covered = [(x.first_link, x.count) for x in frames]
            require(all(n <= cap for _, n in covered), f"§16.5: a SNAPSHOT_IMU over {cap} records: {covered}")
            links = [x.first_link + k for x in frames for k in range(x.count)]
            require(links == want_links, f"§13.2: SNAPSHOT_IMU frames of counter 0x{c0:04X} cover links "
                                         f"{covered}, the runs are {runs} (each link once, ascending)")
            require(not passed, f"§13.1: the chip's own {type(passed[0]).__name__ if passed else ''} (link {link}) "
                                f"was passed on beside the SNAPSHOT_IMU that packs its link")
            for x in frames:
                counts, status, t_us, gyro, mag = x.arrays()
                for k in range(x.count):
                    ln = x.first_link + k
                    st = int(status[k])
                    if ln == link:
                        require(not st & SampleStatus.INVALID,
                                f"§16.5: the streaming chip's link {ln} is INVALID (the gateway did not get its "
                                f"record: did it configure the chip to format {int(fmt)}?)")
                    else:
                        zero = (counts[k].tolist() == [0, 0, 0] and gyro[k].tolist() == [0, 0, 0]
                                and (mag is None or mag[k].tolist() == [0, 0, 0]))
                        require(st & SampleStatus.INVALID and zero and int(t_us[k]) == TIME_UNKNOWN,
                                f"§16.1: link {ln} (no chip streams there) is status 0x{st:X}, counts "
                                f"{counts[k].tolist()}, gyro {gyro[k].tolist()}, time_us {int(t_us[k])}: not an "
                                f"INVALID record (zeros, time_us -32768)")
    finally:
        s.port.send(Stop(chip_node))
        s.port.send(Reset(chip_node))
        s.collect(s.timeout_s)
    return (f"format {int(fmt)}, runs {runs}: every link once per counter; the chip on link {link} valid, the rest "
            f"INVALID records; no record passed on")
