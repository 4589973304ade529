"""Checks while STREAMING: SYNC and SAMPLE (docs §4.3, §4.12, §5), and the broadcasts that change state
(§4.6, §4.12; only with --allow-broadcast)."""

from __future__ import annotations

import math
import statistics

from protocol.constants import SampleStatus
from protocol.messages import (Assign, Capability, ChipState, Config, ImuSample, Info, MsgType, Nack, NackReason,
                               Sample, Start, Stop, Sync)
from protocol.state import SYNC_REPLY_DEADLINE_S

from ..session import acked, HEARTBEAT_MS, require, SAMPLES, Session, Skip

from .registry import should, check, SHOULD_NOT_MET


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
        # behind a SYNC-source gateway an answer to the SYNC before may arrive after this one: a packing
        # gateway has until 10 ms after a SYNC (§13.2, §14), longer than a fast source's period
        smp = [(t, m) for t, m in smp if not _answers_earlier_sync(s, t, m, c)]
        require(len(smp) == 1, f"SYNC 0x{c:04X}: {len(smp)} SAMPLE {[m for _, m in smp][:3]}")
        require(smp[0][1].counter == c, f"SYNC 0x{c:04X} answered with counter 0x{smp[0][1].counter:04X}")
        lat.append(smp[0][0] - t0)
    extra = [m for _, m in s.collect(s.timeout_s) if isinstance(m, SAMPLES)]
    if s.sync_gateway is None:
        require(not extra, f"SYNCs answered twice: {len(extra)} extra SAMPLE (counters {[m.counter for m in extra][:5]})")
    med = statistics.median(lat) * 1000
    limit = SYNC_REPLY_DEADLINE_S * 1000 + s.slack_ms
    timing = (f"{len(lat)} SYNC, median {med:.2f} ms, max {max(lat) * 1000:.2f} ms (host-measured, includes the port"
              + (", and the packing gateway's collection)" if s.packing_gateway else ")"))
    return should(s, med <= limit, f"the median SYNC->SAMPLE is over 2 ms + {s.slack_ms:g} ms slack", timing)


def _answers_earlier_sync(s: Session, t: float, m, c: int) -> bool:
    """``m`` (arrived at ``t``, while the suite waited for the answer to SYNC ``c``) carries the counter of
    a SYNC heard before ``c``: an answer to that SYNC, not a second answer to ``c``. A packing gateway
    has until 10 ms after a SYNC (§13.2, §14) — longer than a fast SYNC source's period — and the host's
    own latency comes on top, so only the counter tells, within the wait for an answer (`answer_s`)."""
    t_sync = s.syncs_heard.get(m.counter)
    return m.counter != c and t_sync is not None and t_sync < s.syncs_heard.get(c, t) and t - t_sync <= s.answer_s


def _samples(s: Session, counters) -> list[Sample | ImuSample]:
    """One SYNC per counter (a SYNC-source gateway's own otherwise); the chip's answer to each: its SAMPLE,
    or the accelerometer part of its IMU record (IMU_SAMPLE, or its link of a SNAPSHOT or SNAPSHOT_IMU:
    a chip is judged by the record format it reaches the host in, whatever its gateway packs)."""
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
        imu = isinstance(m, ImuSample)  # SATURATED covers the whole record: every count sent (§16.1)
        if imu:
            rails = rails or any(v in (-32768, 32767) for v in m.gyro + (m.mag or ()))
        require(rails == bool(m.status & SampleStatus.SATURATED),
                f"SATURATED {'clear' if rails else 'set'} for counts {(m.x, m.y, m.z)}"
                + (f", gyro {m.gyro}, mag {m.mag}" if imu else ""))
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
            t0 = s.port.now()
            (m,) = _samples(s, [c])
            if not m.status & SampleStatus.STALE:
                fresh = m
                break
            stale += 1
            s.port.sleep(max(0.0, 1 / 145 - (s.port.now() - t0)))  # SYNC no faster than rate_hz
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
        s.drain()
        t0 = s.port.send(Sync(counter=7))
        got = [(t0, Sync(counter=7))] + s.collect(s.timeout_s)
    else:  # the gateway's next SYNC: nothing for it from the chip
        got = s.collect(s.gateway_sync_wait_s, lambda ms: sum(isinstance(m, Sync) for m in ms) >= 2, syncs=True)
    # an answer after STOP is one to a SYNC heard after STOP's ACK; a packing gateway's SNAPSHOT for a SYNC
    # before it may still arrive (up to 10 ms after that SYNC, §13.2, §14), and so may a link of its INVALID
    # because the stopped chip did not answer (§13.2: a link not heard)
    after = set()
    ans = []
    for _t, m in got:
        if isinstance(m, Sync):
            after.add(m.counter)
        elif isinstance(m, SAMPLES) and m.counter in after \
                and not (s.packing_gateway and m.status == SampleStatus.INVALID and (m.x, m.y, m.z) == (0, 0, 0)):
            ans.append(m)
    require(ans == [], f"SYNC after STOP answered {ans}")


@check("4.4", "uptime_s counts from power-on: RESET does not restart it",
       "a host cannot tell a protocol RESET from a real reboot (a brown-out) by uptime going backwards",
       "keep the uptime counter across RESET; restart it only at power-on")
def c_uptime(s: Session):
    s.ensure_idle()
    u1 = s.status().uptime_s
    deadline = s.port.now() + 3.0
    while u1 < 2 and s.port.now() < deadline:  # a chip (re)started under a second ago: wait for evidence
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
