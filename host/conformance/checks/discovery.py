"""Checks of discovery, identity and BOOT (docs §3, §4.1, §4.2, §4.10, §4.13, §4.14, §8.2)."""

from __future__ import annotations

import statistics

from protocol.messages import (Announce, Assign, Capability, ChipState, GatewayInfo, GetInfo, Info, MsgType,
                               Nack, NackReason, NODE_PROVISIONAL_MAX, NODE_PROVISIONAL_MIN, PROTOCOL_VERSION,
                               provisional_node, RESERVED_CAPABILITIES, Reset, Start)
from protocol.state import ANNOUNCE_PERIOD_S, TIMER_TOLERANCE

from ..session import acked, CheckFailed, require, RunAborted, Session

from .registry import should, check, PROFILES


# ---------------------------------------------------------------------------------------------
# Discovery, identity, BOOT
# ---------------------------------------------------------------------------------------------

def discover(s: Session, kind: str) -> str:
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
    detail = discover(s, "chip")
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
    return should(s, s.cur == rec, f"0x{s.cur:04X} is not provisional_node(uid, 0) = 0x{rec:04X} after RESET",
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
