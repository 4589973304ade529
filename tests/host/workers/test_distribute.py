"""`host.workers.distribute` without I/O: the counter sequence of one sheet (exact counts, wrap included),
the sharding of sheets among workers, and `SheetWork` turning snapshot payloads into one estimate
payload each."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from host.workers.distribute import Sequence, SheetWork, parse_sheets, parse_worker, shard
from host.publish.zenoh_pub import encode_snapshot
from protocol.lattice import Lattice

HDR = "<4sBBHHIHQdd"  # docs/distribution.md


def test_a_sequence_counts_lost_duplicate_and_old_snapshots_exactly():
    q = Sequence()
    kinds = [q.see(c) for c in (5, 6, 7, 10, 10, 9, 11, 15)]
    assert kinds == ["first", "next", "next", "gap", "duplicate", "old", "next", "gap"]
    assert (q.received, q.lost, q.gaps, q.duplicates, q.old) == (8, 2 + 3, 2, 1, 1)
    assert (q.first, q.last) == (5, 15)


def test_a_sequence_follows_the_16_bit_counter_through_its_wrap():
    q = Sequence()
    kinds = [q.see(c) for c in (65534, 65535, 0, 1, 3)]
    assert kinds == ["first", "next", "next", "next", "gap"]
    assert (q.lost, q.gaps) == (1, 1)
    assert q.see(65535) == "old"  # behind the last across the wrap, not 65,534 ahead


def test_a_restarted_host_is_a_new_sequence_not_lost_or_old_snapshots():
    q = Sequence()
    p = 1 / 145
    # 145 Hz from counter 40,000; the host restarts 2 s later at 0, then again at 50,000 after 1 s
    seen = [q.see(40_000 + k, 100.0 + k * p) for k in range(10)]
    seen += [q.see(k, 102.0 + k * p) for k in range(5)]  # behind in counter, ahead in time
    seen += [q.see(50_000, 103.0)]  # 49,996 counters ahead in 1 s: not 49,995 lost
    seen += [q.see(50_003, 103.0 + 3 * p)]  # a real gap of 2
    seen += [q.see(50_001, 103.0 + p)]  # an old one come late: older in time too
    assert seen == ["first"] + ["next"] * 9 + ["restart"] + ["next"] * 4 + ["restart", "gap", "old"]
    assert (q.restarts, q.lost, q.gaps, q.old, q.duplicates) == (2, 2, 1, 1, 0)
    assert q.see(50_003, 103.0 + 3 * p) == "duplicate"
    # a short skip in little time (a late SYNC, then an early one) is still a lost snapshot
    assert q.see(50_005, 103.0 + 3.6 * p) == "gap" and (q.lost, q.restarts) == (3, 2)


def test_sharding_is_crc32_of_the_name_and_splits_every_sheet_to_one_worker():
    names = [f"sheet_{k}" for k in range(40)]
    for n in (1, 2, 3, 8):
        got = [shard(s, n) for s in names]
        assert got == [zlib.crc32(s.encode()) % n for s in names]  # the documented rule, from zlib
        assert all(0 <= g < n for g in got)
    assert {shard(s, 2) for s in names} == {0, 1}


@pytest.mark.parametrize("text", ["2/2", "-1/2", "1", "a/b", "0/0", "0/2000"])
def test_a_bad_worker_value_is_refused(text):
    with pytest.raises(ValueError, match="--worker"):
        parse_worker(text)


def test_a_selection_takes_names_patterns_and_a_workers_share():
    from host.workers.distribute import Selection
    sel = Selection.of(parse_sheets("arm,leg_*"), None)
    assert (sel.names, sel.patterns) == (("arm",), ("leg_*",)) and sel.keys == ["capsheet/*/snapshot"]
    assert [sel.takes(s) for s in ("arm", "leg_1", "leg", "arms")] == [True, True, False, False]
    assert Selection.of(["a", "b"], None).keys == ["capsheet/a/snapshot", "capsheet/b/snapshot"]
    names = [f"leg_{k}" for k in range(20)]
    shares = [[s for s in names if Selection.of(["leg_*"], (i, 3)).takes(s)] for i in range(3)]
    assert sorted(sum(shares, [])) == sorted(names)  # each sheet to exactly one worker
    assert shares[1] == [s for s in names if zlib.crc32(s.encode()) % 3 == 1]
    assert Selection.of(None, None).takes("anything")


def test_sheets_are_names_none_twice():
    assert parse_sheets("a,b.c") == ["a", "b.c"]
    for bad in ("a,a", "a/b", "", "a,,b"):
        with pytest.raises(ValueError):
            parse_sheets(bad)


class _Snap:
    def __init__(self, counter, readings, valid):
        self.counter, self.timestamp, self.wall_time = counter, 100.0 + counter / 145, 1.7e9 + counter / 145
        self.readings, self.valid = readings, valid
        self.status = np.zeros(valid.shape[0], np.uint8)


def _flat(lat: Lattice, rng) -> np.ndarray:
    """A flat sheet held level: every link reads gravity along its sensor z, with noise."""
    return np.tile([0.0, 0.0, 9.81], (lat.n_links, 1)) + rng.normal(0, 0.05, (lat.n_links, 3))


def test_sheet_work_makes_one_estimate_per_snapshot_in_order_and_flags_one_it_cannot_make():
    lat = Lattice(3, 4)
    rng = np.random.Generator(np.random.MT19937(3))
    w = SheetWork("s", uncertainty_period_s=None)
    w.set_info({"rows": 3, "cols": 4, "link_length_m": 0.02})
    valid = np.ones(lat.n_links, bool)
    outs = []
    for c in (7, 8, 9, 12):
        outs.append(w.work(encode_snapshot(_Snap(c, _flat(lat, rng), valid), 3, 4), now=float(c)))
    outs.append(w.work(encode_snapshot(_Snap(13, _flat(lat, rng), np.zeros(lat.n_links, bool)), 3, 4), now=13.0))
    assert w.work(encode_snapshot(_Snap(13, _flat(lat, rng), valid), 3, 4), now=14.0) is None  # duplicate
    assert w.work(b"CSNP junk", now=15.0) is None
    heads = [struct.unpack_from(HDR, o) for o in outs]
    assert [h[7] for h in heads] == [7, 8, 9, 12, 13]
    assert all(h[0] == b"CEST" and (h[3], h[4], h[5]) == (3, 4, 12) for h in heads)
    assert [h[2] for h in heads] == [0, 0, 0, 0, 2]  # the empty snapshot: flag 2, not estimated
    for o in outs[:4]:
        j = np.frombuffer(o, "<f4", 36, 40).reshape(3, 4, 3)
        links = np.linalg.norm(np.diff(j, axis=1), axis=2)
        np.testing.assert_allclose(links, 0.02, rtol=0.02)  # the link length from the info, metres
        assert np.ptp(j[..., 2]) < 0.002  # flat
    assert np.isnan(np.frombuffer(outs[4], "<f4", 36, 40)).all()
    s = w.summary()
    assert (s["received"], s["estimated"], s["not_estimated"], s["lost"], s["gaps"], s["duplicates"],
            s["bad_payloads"]) == (6, 4, 1, 2, 1, 1, 1)
    assert s["not_estimated_reasons"] == {"no valid link": 1}


def test_sheet_work_refuses_an_info_without_the_lattice_and_a_snapshot_of_another_size():
    w = SheetWork("s")
    with pytest.raises(ValueError, match="link_length_m"):
        w.set_info({"rows": 3, "cols": 3})
    w.set_info({"rows": 3, "cols": 3, "link_length_m": 0.01})
    lat = Lattice(4, 4)
    snap = _Snap(1, np.zeros((lat.n_links, 3)), np.ones(lat.n_links, bool))
    assert w.work(encode_snapshot(snap, 4, 4), now=0.0) is None
    assert w.bad_payloads == 1 and "4x4 snapshot for a 3x3 sheet" in w.last_bad


def test_a_6_axis_snapshot_carries_its_gyroscopes_magnetometers_and_sample_times():
    from host.publish.zenoh_pub import decode_snapshot
    lat = Lattice(3, 3)
    n = lat.n_links
    rng = np.random.Generator(np.random.MT19937(5))
    snap = _Snap(4, _flat(lat, rng), np.ones(n, bool))
    snap.gyro, snap.mag = rng.normal(0, 0.3, (n, 3)), rng.normal(0, 4e-5, (n, 3))
    snap.sample_time_s = rng.uniform(0, 0.005, n)
    snap.gyro[2] = np.nan  # a link without an IMU record
    payload = encode_snapshot(snap, 3, 3)
    assert len(payload) == 40 + 14 * n + 12 * n + 12 * n + 4 * n  # docs/distribution.md
    assert struct.unpack_from(HDR, payload)[2] == 1 | 2 | 4
    d = decode_snapshot(payload)
    for name in ("gyro", "mag", "sample_time_s"):
        np.testing.assert_array_equal(d[name], getattr(snap, name).astype(np.float32))
    snap.mag = None
    d = decode_snapshot(encode_snapshot(snap, 3, 3))
    assert d["mag"] is None and d["gyro"].shape == (n, 3)
    w = SheetWork("s", method="fused")
    w.set_info({"rows": 3, "cols": 3, "link_length_m": 0.01})
    plain = _Snap(5, _flat(lat, rng), np.ones(n, bool))
    out = w.work(encode_snapshot(plain, 3, 3), now=0.0)  # no gyroscopes: flagged, counted
    assert struct.unpack_from(HDR, out)[2] == 2 and w.not_estimated == {"no gyroscopes (--method fused)": 1}
