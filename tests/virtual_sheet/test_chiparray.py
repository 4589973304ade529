"""The vectorised chip array against N reference `ChipModel` s: the same random command sequences
(every host command, SYNC, garbage, time passing, chip faults and timers) must give identical
frames, byte for byte, and identical chip state — the discipline of C == Python, for the array.
Then the same at the sheet + gateway level (per-chip and packed, serial and CAN)."""

from __future__ import annotations

import numpy as np
import pytest
from cobs import cobs
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.can import to_can
from protocol.crc import crc16_rows
from protocol.framing import decode_frame, encode
from protocol.messages import (Announce, Assign, CalRead, CalWrite, ChipState, Config, GetInfo, Info, Reset,
                               Start, Status, Stop, Sync, provisional_node)
from protocol.state import ANNOUNCE_PERIOD_S
from virtual_sheet.chip import ChipModel
from virtual_sheet.chiparray import ChipArray, cobs_encode_batch, encode_samples_serial
from virtual_sheet.faults import DriftingSensor, FaultSpec, FaultStats, wrap_chip
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet, make_uids


def _sensor_value(now_s: float, k: int) -> tuple[tuple[int, int, int], int]:
    """A deterministic sensor: counts from (time, chip), INVALID now and then, other bits too."""
    h = (int(round(now_s * 1e6)) * 2654435761 + k * 40503) & 0xFFFFFFFF
    x, y, z = (h & 0xFFF) - 2048, ((h >> 12) & 0xFFF) - 2048, ((h >> 3) % 4000) - 2000
    status = 0x8 if h % 29 == 0 else (h >> 24) & 0x7
    return (x, y, z), status


def _batch(now_s: float, idx: np.ndarray):
    vals = [_sensor_value(now_s, int(k)) for k in idx]
    counts = np.array([v[0] for v in vals], dtype=np.int64).reshape(-1, 3)
    return counts, np.array([v[1] for v in vals], dtype=np.int64)


GAPS = st.one_of(st.sampled_from([0, 1, 2, 3, 0x7FFD, 0x7FFE, 0x7FFF, 0x8000, 0x8001, 0xFFFE, 0xFFFF, 300]),
                 st.integers(0, 0xFFFF))
OPS = st.one_of(
    st.tuples(st.just("sync"), st.integers(0, 0xFFFF)),
    st.tuples(st.just("sync+1")),
    st.tuples(st.just("sync+1")),
    st.tuples(st.just("sync+1")),
    st.tuples(st.just("syncgap"), GAPS),
    st.tuples(st.just("bringup"), st.integers(0, 3), st.sampled_from([0, 200, 1000]), st.integers(0, 12)),
    st.tuples(st.just("bringup"), st.integers(0, 3), st.sampled_from([0, 200, 1000]), st.integers(0, 12)),
    st.tuples(st.just("poll")),
    st.tuples(st.just("due")),
    st.tuples(st.just("wait"), st.floats(0.0005, 1.5)),
    st.tuples(st.just("assign"), st.integers(0, 7), st.integers(0, 40), st.booleans()),
    st.tuples(st.just("config"), st.integers(0, 7), st.integers(0, 4), st.integers(0, 4), st.integers(0, 5000),
              st.sampled_from([0, 1, 200, 1000])),
    st.tuples(st.just("start"), st.integers(-1, 7)),
    st.tuples(st.just("stop"), st.integers(-1, 7)),
    st.tuples(st.just("reset"), st.integers(-1, 7)),
    st.tuples(st.just("getinfo"), st.integers(-1, 7)),
    st.tuples(st.just("calread"), st.integers(0, 7), st.integers(0, 3)),
    st.tuples(st.just("calwrite"), st.integers(0, 7), st.integers(0, 3), st.integers(-500, 500), st.integers(0, 1)),
    st.tuples(st.just("garbage"), st.binary(min_size=1, max_size=20)),
)


def _message(op, refs, counter):
    """The host frame of an abstract op, built from the reference chips' state."""
    kind = op[0]

    def node_of(j):
        return 0 if j < 0 else refs[j % len(refs)].node
    if kind == "sync":
        return Sync(counter=op[1])
    if kind == "sync+1":
        return Sync(counter=counter)
    if kind == "syncgap":
        return Sync(counter=(counter + op[1]) & 0xFFFF)
    if kind == "assign":
        _, j, link, right_uid = op
        c = refs[j % len(refs)]
        return Assign(c.node, new_node=1 + (j % len(refs)), link=link,
                      uid_low=(c.uid & 0xFFFFFFFF) if right_uid else 0x1234)
    if kind == "config":
        _, j, rng, flt, rate, hb = op
        return Config(node_of(j), rate_hz=rate, range=rng, filter=flt, heartbeat_ms=hb)
    if kind == "start":
        return Start(node_of(op[1]))
    if kind == "stop":
        return Stop(node_of(op[1]))
    if kind == "reset":
        return Reset(node_of(op[1]))
    if kind == "getinfo":
        return GetInfo(node_of(op[1]))
    if kind == "calread":
        return CalRead(node_of(op[1]), min(op[2], 2))
    if kind == "calwrite":
        _, j, axis, off, flags = op
        return CalWrite(node_of(j), min(axis, 2), flags, off, 1000.0 + off)
    raise AssertionError(kind)


def _state(c):
    return (int(c.state), c.node, c.link, c.streaming, c.last_counter, c.missed_syncs, c.rx_errors, c.range,
            c.rate_hz, c.filter, c.heartbeat_ms, c.configured, c.salt, c.next_heartbeat_s, c.next_announce_s,
            list(c.cal), c.powered)


@settings(max_examples=60)
@given(n=st.integers(1, 6), transport=st.sampled_from(["serial", "can"]), seed=st.integers(0, 2**16),
       dead=st.lists(st.integers(0, 5), max_size=2), dead_after=st.floats(0, 3), babble=st.lists(st.integers(0, 5), max_size=2),
       flood=st.booleans(), drift=st.lists(st.integers(0, 5), max_size=2),
       ops=st.lists(OPS, min_size=8, max_size=60))
def test_array_answers_exactly_as_n_chip_models(n, transport, seed, dead, dead_after, babble, flood, drift, ops):
    can = transport == "can"
    uids = make_uids(n, seed)
    cals = [((k, 1000.0 + k), (-k, 1010.0), (2 * k, 990.0)) for k in range(n)]
    spec = FaultSpec(dead_chip=tuple(d for d in dead if d < n), dead_after_s=dead_after,
                     babble_chip=tuple(b for b in babble if b < n), babble_mode="flood" if flood else "garbage",
                     seed=seed, drift=0.3)
    drift = {d for d in drift if d < n}
    ref_stats, arr_stats = FaultStats(), FaultStats()

    def src(k, stats):
        s = lambda now_s, _k=k: _sensor_value(now_s, _k)  # noqa: E731
        return DriftingSensor(s, 0.3, stats) if k in drift else s
    refs = [wrap_chip(ChipModel(u, src(k, ref_stats), transport=transport, calibration=cals[k]), k, spec, ref_stats,
                      can=can) for k, u in enumerate(uids)]
    arr = ChipArray(uids, _batch, transport=transport, calibrations=cals,
                    sensors={k: src(k, arr_stats) for k in drift}, faults=spec, fault_stats=arr_stats)
    now = 0.0
    got_ref = [f for c in refs for f in c.power_on(now)]
    got_arr = arr.power_on(now)
    assert got_arr == got_ref
    counter = 0
    for op in ops:
        if op[0] == "wait":  # time passes, then the timers are served (re-ANNOUNCE, heartbeats)
            now += op[1]
            want = [f for c in refs for f in c.poll(now)]
            assert arr.poll(now) == want
            continue
        if op[0] == "due":  # time jumps to exactly the next timer of some chip (a >= edge)
            inner = [c.inner if hasattr(c, "inner") else c for c in refs]
            due = [c.next_announce_s if c.state == ChipState.BOOT else c.next_heartbeat_s
                   for c in inner if c.powered]
            due = [t for t in due if t is not None and t >= now]
            if due:
                now = min(due)
            want = [f for c in refs for f in c.poll(now)]
            assert arr.poll(now) == want
            continue
        now += 0.001
        if op[0] == "poll":
            want = [f for c in refs for f in c.poll(now)]
            assert arr.poll(now) == want
            continue
        if op[0] == "garbage":
            frame = op[1] + b"\x00" if not can else to_can(GetInfo(0))._replace(data=op[1][:8])
            decoded = refs[0].decode(frame)
            want = [f for c in refs for f in c.handle(frame, now, decoded)]
            assert arr.handle(frame, now, decoded) == want
            continue
        if op[0] == "bringup":  # every chip assigned (its own link), configured, started
            _, rng, hb, n_sync = op
            msgs = [Assign(c.node, new_node=1 + k, link=k, uid_low=c.uid & 0xFFFFFFFF) for k, c in enumerate(refs)]
            msgs += [Config(1 + k, rate_hz=145, range=rng, filter=0, heartbeat_ms=hb) for k in range(n)]
            msgs.append(Start(0))
            msgs += [Sync(counter=(counter + i) & 0xFFFF) for i in range(n_sync)]
            counter = (counter + n_sync) & 0xFFFF
            for msg in msgs:
                frame = to_can(msg) if can else encode(msg)
                if msg.node == 0:
                    want = [f for c in refs for f in c.handle(frame, now, msg)]
                    assert arr.handle(frame, now, msg) == want
                else:
                    want = [f for c in refs if c.node == msg.node for f in c.handle(frame, now, msg)]
                    assert arr.handle_node(msg.node, frame, now, msg) == want
            continue
        msg = _message(op, refs, counter)
        if isinstance(msg, Sync):
            counter = (msg.counter + 1) & 0xFFFF
        frame = to_can(msg) if can else encode(msg)
        if msg.node == 0:
            want = [f for c in refs for f in c.handle(frame, now, msg)]
            assert arr.handle(frame, now, msg) == want, op
        else:
            want = [f for c in refs if c.node == msg.node for f in c.handle(frame, now, msg)]
            assert arr.handle_node(msg.node, frame, now, msg) == want, op
        assert [_state(c) for c in arr.views] == [_state(c.inner if hasattr(c, "inner") else c) for c in refs]
    assert arr_stats.as_dict() == ref_stats.as_dict()


def test_a_broken_batch_encoder_is_caught_by_the_equivalence_discipline():
    """The check above compares bytes: a one-byte CRC error in the batch encoder would trip it."""
    rng = np.random.Generator(np.random.MT19937(3))
    node = rng.integers(1, 0x8000, 50)
    word = rng.integers(0, 1 << 40, 50)
    rows = encode_samples_serial(node, 0x1234, word)
    from protocol.messages import Sample
    for r, nd, w in zip(rows, node.tolist(), word.tolist()):
        x, y, z = [((w >> s & 0xFFF) ^ 0x800) - 0x800 for s in (0, 12, 24)]
        assert bytes(r) == encode(Sample(nd, 0x1234, x, y, z, w >> 36 & 0xF))
    broken = rows.copy()
    broken[0, 12] ^= 1
    assert bytes(broken[0]) != bytes(rows[0])


def _byte_heavy(bits: int):
    """Integers of ``bits`` bits built byte by byte, each byte often 0x00 or 0xFF (COBS and CRC edges)."""
    return st.lists(st.one_of(st.just(0), st.just(0xFF), st.integers(0, 255)), min_size=bits // 8,
                    max_size=bits // 8).map(lambda bs: int.from_bytes(bytes(bs), "little"))


@given(st.lists(st.tuples(_byte_heavy(16).filter(lambda v: v != 0xFFFF), _byte_heavy(40)), min_size=1, max_size=40),
       _byte_heavy(16))
def test_batch_sample_frames_are_the_frames_the_protocol_encodes(chips, counter):
    """The table-driven SAMPLE encoder against `protocol.framing.encode`, frame by frame."""
    from protocol.messages import Sample
    node = np.array([nd for nd, _ in chips], dtype=np.int64)
    word = np.array([w for _, w in chips], dtype=np.int64)
    rows = encode_samples_serial(node, counter, word)
    for r, (nd, w) in zip(rows, chips):
        x, y, z = [((w >> s & 0xFFF) ^ 0x800) - 0x800 for s in (0, 12, 24)]
        assert bytes(r) == encode(Sample(nd, counter, x, y, z, w >> 36 & 0xF))
    assert rows.shape == (len(chips), 15)


@given(st.lists(st.binary(min_size=13, max_size=13), min_size=1, max_size=20))
def test_batch_cobs_and_crc_match_the_libraries(blocks):
    import binascii
    rows = np.frombuffer(b"".join(blocks), np.uint8).reshape(len(blocks), 13)
    assert [bytes(r) for r in cobs_encode_batch(rows)] == [cobs.encode(b) for b in blocks]
    assert crc16_rows(rows).tolist() == [binascii.crc_hqx(b, 0xFFFF) for b in blocks]


# ------------------------------------------------------------------------------------ sheet level

def _run_gateway(engine, transport, packed, faults, n_sync=40, lattice="5x4"):
    sheet = VirtualSheet("grow", lattice, seed=4, noise=1.0, transport=transport, fd=packed and transport == "can",
                         faults=faults, engine=engine, scene_rate_hz=20.0)
    gws = [Gateway(sheet, blk, packed=packed, stream=b) for b, blk in enumerate(sheet.split(2 if transport == "can" else 1))]
    out = []
    for gw in gws:
        gw.power_on(0.0)
        gw.commission(0.001)
    t = 0.002
    for c in range(n_sync):
        t += 1 / 145
        for gw in gws:
            frame = to_can(Sync(counter=c)) if transport == "can" else encode(Sync(counter=c))
            if transport == "can":
                gw.receive(frame, t)
            else:
                gw.feed(frame, t)
            gw.poll(t)
            out.append(gw.pop_output(t + 0.01))
    return out, sheet.fault_stats.as_dict(), [sheet.truth(c).tobytes() for c in range(n_sync)]


@pytest.mark.parametrize("transport,packed", [("serial", False), ("serial", True), ("can", False), ("can", True)])
@pytest.mark.parametrize("faults", [None, "dead_chip=3,dead_after_s=0.1,babble_chip=5,drift_chip=7,drift_late_ms=3,"
                                          "bitflip=1e-4,drop_frame=0.02,dup_frame=0.02,reorder=0.02,jitter_ms=2,seed=2"])
def test_sheet_with_the_array_engine_sends_what_the_per_chip_sheet_sends(transport, packed, faults):
    a = _run_gateway("array", transport, packed, faults)
    b = _run_gateway("chips", transport, packed, faults)
    assert a[0] == b[0]  # every frame to the host, byte for byte, in order
    assert a[1] == b[1]  # every injected fault counted alike
    assert a[2] == b[2]  # the truth of every counter
    assert sum(len(x) for x in a[0]) > 40


def _run_gateways(engine, n_gw, noise, counters, lattice="6x5", spy=None):
    """A packed serial sheet over ``n_gw`` gateways (each answering for its block of chips), every
    gateway given the SYNCs ``counters`` in turn; each gateway's output per SYNC and the chips'
    state. ``spy``: called with each `ChipArray._answer_some` call's chips."""
    sheet = VirtualSheet("grow", lattice, seed=6, noise=noise, engine=engine, scene_rate_hz=20.0)
    if spy is not None:
        arr = sheet.array
        some = arr._answer_some
        arr._answer_some = lambda c, t, ans: (spy(ans), some(c, t, ans))[1]
    gws = [Gateway(sheet, blk, packed=True, stream=b) for b, blk in enumerate(sheet.split(n_gw))]
    out = []
    for gw in gws:
        gw.power_on(0.0)
        gw.commission(0.001)
    t = 0.002
    for c in counters:
        t += 1 / 145
        for gw in gws:
            gw.feed(encode(Sync(counter=c)), t)
            gw.poll(t)
            out.append(gw.pop_output(t + 0.01))
    views = sheet.array.views if engine == "array" else sheet.chips
    state = [(c.missed_syncs, c.last_counter, int(c.state)) for c in views]
    return out, state


@pytest.mark.parametrize("noise", [1.0, 400.0])  # 400 % g: counts at the rails, SATURATED set
def test_a_streaming_sheet_over_several_gateways_answers_as_its_chip_models(noise):
    """Each gateway's chips answered from the arrays alone (`ChipArray._answer_some`, every chip
    streaming) send the same frames, byte for byte, and keep the same missed-SYNC counts as
    per-chip models, through counter gaps and a wrap."""
    counters = [65530 + k & 0xFFFF for k in range(12)] + [20, 21, 25, 300, 301]
    calls = []
    a = _run_gateways("array", 3, noise, counters, spy=lambda ans: calls.append(ans.size))
    b = _run_gateways("chips", 3, noise, counters)
    assert len(calls) >= 3 * len(counters) and sum(calls) >= 49 * len(counters)  # the path was taken
    assert a[0] == b[0]
    assert a[1] == b[1]
    assert sum(len(x) for x in a[0]) > len(counters)
    assert any(m for m, _, _ in a[1])  # the gaps were counted


# ------------------------------------------------------------------------ directed edge cases
# The random sequences above rarely land on these edges (a float time equal to a timer's due
# time; a counter gap just below half the counter space while missed_syncs is not yet saturated),
# so each is also driven on purpose, against hand-written expectations and the reference model.

def _steady(now_s: float, idx: np.ndarray):
    """A sensor that always answers (never INVALID): every chip stays STREAMING."""
    return np.tile(np.array([[5, -7, 1000]], dtype=np.int64), (idx.size, 1)), np.zeros(idx.size, dtype=np.int64)


def _pair(n: int, seed: int = 7):
    uids = make_uids(n, seed)
    refs = [ChipModel(u, lambda now_s: ((5, -7, 1000), 0)) for u in uids]
    return uids, refs, ChipArray(uids, _steady)


def _both(arr, refs, msg, now):
    """Send ``msg`` to the array and the reference chips; both answers, asserted equal."""
    frame = encode(msg)
    if msg.node == 0:
        want = [f for c in refs for f in c.handle(frame, now, msg)]
        got = arr.handle(frame, now, msg)
    else:
        want = [f for c in refs if c.node == msg.node for f in c.handle(frame, now, msg)]
        got = arr.handle_node(msg.node, frame, now, msg)
    assert got == want
    return got


# gap = SYNCs skipped between two answered counters; docs/protocol.md: a gap of 0x7FFF or more
# (an older or repeated counter) adds nothing, anything less adds, saturating at 255
@pytest.mark.parametrize("gap,missed", [(0, 0), (1, 1), (254, 254), (255, 255), (300, 255), (0x7FEF, 255),
                                        (0x7FF0, 255), (0x7FFE, 255), (0x7FFF, 0), (0x8000, 0), (0xFFFF, 0)])
@pytest.mark.parametrize("answering", ["all", "some"])  # the whole-array SYNC, and the gathered one
def test_missed_syncs_of_a_counter_gap(gap, missed, answering):
    n = 3
    uids, refs, arr = _pair(n)
    for c in refs:
        c.power_on(0.0)
    arr.power_on(0.0)
    for k, c in enumerate(refs):
        _both(arr, refs, Assign(c.node, new_node=1 + k, link=k, uid_low=c.uid & 0xFFFFFFFF), 0.01)
    _both(arr, refs, Start(0), 0.02)
    if answering == "some":
        _both(arr, refs, Stop(n), 0.02)  # the last chip stops: the others answer alone
    first = 1000
    assert len(_both(arr, refs, Sync(counter=first), 0.03)) == (n if answering == "all" else n - 1)
    _both(arr, refs, Sync(counter=(first + 1 + gap) & 0xFFFF), 0.04)
    answered = range(n) if answering == "all" else range(n - 1)
    assert [arr.views[k].missed_syncs for k in answered] == [missed] * len(answered)
    assert [refs[k].missed_syncs for k in answered] == [missed] * len(answered)
    if answering == "some":
        assert arr.views[n - 1].missed_syncs == 0
    # and on the wire: the STATUS heartbeat carries it (byte 3 of the payload)
    st = arr.poll(0.01 + 1.0)
    assert st == [f for c in refs for f in c.poll(0.01 + 1.0)]
    assert [decode_frame(f[:-1]).missed_syncs for f in st] == [missed] * len(answered) + [0] * (n - len(answered))


def test_timers_fire_at_exactly_their_due_time():
    """ANNOUNCE repeats at boot + ANNOUNCE_PERIOD_S, not a tick later; STATUS at assign + period."""
    n = 3
    uids, refs, arr = _pair(n)
    t0 = 0.25
    for c in refs:
        c.power_on(t0)
    arr.power_on(t0)
    due = t0 + ANNOUNCE_PERIOD_S
    before = float(np.nextafter(due, 0.0))
    assert arr.poll(before) == [] == [f for c in refs for f in c.poll(before)]
    got = arr.poll(due)
    assert got == [f for c in refs for f in c.poll(due)]
    msgs = [decode_frame(f[:-1]) for f in got]
    assert [type(m) for m in msgs] == [Announce, Info] * n
    assert [m.node for m in msgs] == [provisional_node(u, 1) for u in uids for _ in (0, 1)]
    assert [m.uid for m in msgs[::2]] == uids
    # assigned at t1: the first heartbeat is due at t1 + 1 s (the default 1000 ms)
    t1 = 2.5
    for k, c in enumerate(refs):
        _both(arr, refs, Assign(c.node, new_node=1 + k, link=k, uid_low=c.uid & 0xFFFFFFFF), t1)
    hb = t1 + 1.0
    before = float(np.nextafter(hb, 0.0))
    assert arr.poll(before) == [] == [f for c in refs for f in c.poll(before)]
    got = arr.poll(hb)
    assert got == [f for c in refs for f in c.poll(hb)]
    assert [(type(m), m.node) for m in (decode_frame(f[:-1]) for f in got)] == [(Status, 1 + k) for k in range(n)]


@pytest.mark.parametrize("engine", ["array", "chips"])
@pytest.mark.parametrize("packed", [False, True])
@pytest.mark.parametrize("faults", [None, "drop_frame=0.05,dup_frame=0.05,seed=3", "drift_chip=2,drift_late_ms=3"])
def test_pop_wire_is_pop_output_joined(engine, packed, faults):
    """What a serial device writes (`pop_wire`, frames kept as one byte string) is what
    `pop_output` hands out frame by frame, and both count the same frames."""
    runs = []
    for wire in (False, True):
        sheet = VirtualSheet("grow", "5x4", seed=4, noise=1.0, faults=faults, engine=engine, scene_rate_hz=20.0)
        gw = Gateway(sheet, packed=packed)
        gw.power_on(0.0)
        gw.commission(0.001)
        data, frames = b"", 0
        t = 0.002
        for c in range(30):
            t += 1 / 145
            gw.feed(encode(Sync(counter=c)), t)
            gw.poll(t)
            if wire:
                d, n = gw.pop_wire(t + 0.002)
            else:
                out = gw.pop_output(t + 0.002)
                d, n = b"".join(out), len(out)
            data += d
            frames += n
        runs.append((data, frames, gw.stats.frames_to_host))
    assert runs[0] == runs[1]
    assert runs[0][1] == runs[0][2] > 30


def _railing(now_s: float, idx: np.ndarray):
    """Counts at the rails on every other chip with no status bit of the sensor's own."""
    c = np.tile(np.array([[5, -7, 1000]], dtype=np.int64), (idx.size, 1))
    c[idx % 2 == 1] = [2047, 0, -2048]
    return c, np.zeros(idx.size, dtype=np.int64)


@pytest.mark.parametrize("sensor", [_steady, _railing])
def test_one_gateways_chips_answer_from_the_arrays_as_the_general_path_does(sensor):
    """`ChipArray._answer_some` against the array's general path (taken when the array is told it
    has scalar sources): the same chips, sample words and missed-SYNC counts for a gateway's
    block, SATURATED set from counts at the rails that the sensor did not flag."""
    uids = make_uids(5, 3)
    twins = [ChipArray(uids, sensor), ChipArray(uids, sensor)]
    sel = np.array([False, True, True, True, False])
    for arr in twins:
        arr.power_on(0.0)
        for k, v in enumerate(arr.views):
            arr.handle_node(v.node, b"", 0.01, Assign(v.node, new_node=1 + k, link=k, uid_low=v.uid & 0xFFFFFFFF))
        arr.handle(b"", 0.02, Start(0))
    twins[1]._no_scalar = False  # the general path
    for c in (7, 8, 11, 12):
        got = [arr.sync_words(b"", Sync(counter=c), 0.03 + c / 145, sel) for arr in twins]
        assert got[0][0].tolist() == got[1][0].tolist() == [1, 2, 3]
        assert got[0][1].tolist() == got[1][1].tolist()
        assert twins[0].missed_syncs.tolist() == twins[1].missed_syncs.tolist()
    assert twins[0].missed_syncs.tolist() == [0, 2, 2, 2, 0]
    words = got[0][1]
    assert (((words >> 36) & 1) == (np.array([1, 2, 3]) % 2 == 1) * (sensor is _railing)).all()  # odd chips rail
