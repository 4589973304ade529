"""Checks of a gateway node (--profile gateway, docs §13, §4.16)."""

from __future__ import annotations


from protocol.constants import SampleStatus
from protocol.messages import (Announce, Assign, CalRead, Capability, ChipState, Config, GatewayFlag,
                               GatewayInfo, GetInfo, Info, Nack, NackReason, PROTOCOL_VERSION,
                               RESERVED_CAPABILITIES, Reset, SAMPLE_FORMAT_CODES, SampleFormat, Snapshot, Start, Stop, Sync)
from protocol.state import GATEWAY_HEARTBEAT_MS, TIMER_TOLERANCE

from ..session import require, Session, Skip

from .discovery import discover, theil_sen_period
from .registry import check


# ---------------------------------------------------------------------------------------------
# Gateways (--profile gateway, docs/protocol.md §13)
# ---------------------------------------------------------------------------------------------

@check("13.1, 4.13", "GET_INFO (broadcast) is answered with ANNOUNCE, INFO (GATEWAY), GATEWAY_INFO",
       "the host cannot find the gateway, so it cannot learn that it packs or drives SYNC",
       "be a node: answer GET_INFO with ANNOUNCE, INFO with capability bit 6 GATEWAY, then one GATEWAY_INFO "
       "per run of links", profiles=("gateway",))
def c_gateway_discover(s: Session):
    detail = discover(s, "gateway")
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
        require(r.sample_format in SAMPLE_FORMAT_CODES,
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


def a_chip_behind(s: Session):
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
    fmts = packed_formats(g)
    if fmts - {SampleFormat.ACCEL_12}:
        raise Skip(f"the gateway packs IMU records (GATEWAY_INFO sample_format {sorted(fmts)}): check of §16.5")
    uid, chip_node, link = a_chip_behind(s)
    runs = sorted((r.first_link, r.link_count) for r in g.runs.values() if r.link_count)
    cap = 202 if s.port.kind == "serial" else 11
    try:
        for c in range(40, 43):
            s.drain()
            if not g.flags & GatewayFlag.SYNC_SOURCE:
                s.port.send(Sync(counter=c))
            got = []
            deadline = s.port.now() + s.answer_s
            want = sum(n for _, n in runs)
            while s.port.now() < deadline:
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


def packed_formats(g) -> set:
    """The sample formats a gateway's runs pack (GATEWAY_INFO ``sample_format``, §4.16, §16.5)."""
    return {int(r.sample_format) for r in g.runs.values() if r.link_count}
