"""Every payload a view or an estimate worker receives is checked before use (host/publish/zenoh_pub.py,
host/cli/view.py, host/cli/subscribe.py): a bad one is a counted event, never a crash, never an
unbounded allocation. The processes run on loopback; the hostile publisher is this test."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from host.publish.zenoh_pub import (HEADER, MAX_PAYLOAD_BYTES, decode_estimate, decode_snapshot,  # noqa: E402
                                    encode_estimate, encode_snapshot)
from host.publish.zenoh_session import open_session  # noqa: E402
from tests import zenoh_meeting  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
#: no Zenoh config of the user's; the worker's meeting point kept (tests/zenoh_meeting.py): the
#: processes meet this test's own sessions there
ENV = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH") or k == zenoh_meeting.VAR}
#: runs a command and prints its peak RSS (kB, Linux) once it has ended: what it allocated, measured
#: by the kernel, not by the code under test
MAXRSS = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
          "print('maxrss_kb', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); "
          "sys.exit(r.returncode)")


def _tag() -> str:
    return f"p{os.getpid()}_{time.monotonic_ns() % 10**6}"


# the 52-byte estimate that crashed ``capsheet view``: a 1x1 lattice, one joint
ONE_BY_ONE = HEADER.pack(b"CEST", 1, 0, 1, 1, 1, 0, 7, 0.0, 0.0) + np.zeros(3, "<f4").tobytes()


def test_the_one_by_one_estimate_is_52_bytes_and_refused():
    assert len(ONE_BY_ONE) == 52
    with pytest.raises(ValueError, match="1x1 lattice"):
        decode_estimate(ONE_BY_ONE)


def _estimate(rows: int, cols: int) -> bytes:
    J = np.zeros((rows, cols, 3))
    J[..., 0], J[..., 1] = np.meshgrid(np.arange(rows) * 0.01, np.arange(cols) * 0.01, indexing="ij")
    return encode_estimate(SimpleNamespace(joints=J), 1, 0.0, time.time(), uncertainty=False)


def test_view_counts_bad_estimates_and_draws_the_good_ones(tmp_path):
    """A 1x1 estimate, a too-big lattice, junk and a payload over the size cap, then good ones:
    ``capsheet view`` names the bad ones in its summary, draws the good ones, exits 0."""
    sheet = _tag()
    robot = tmp_path / "robot.toml"
    robot.write_text(f'[[sheet]]\nname = "{sheet}"\ntranslation = [0, 0, 0]\nrpy_deg = [0, 0, 0]\n')
    view = subprocess.Popen([sys.executable, "-m", "host.cli", "view", "--config", str(robot), "--port", "0",
                             "--rate", "50", "--duration", "6"], stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env=ENV)
    s = open_session(None)
    try:
        line = view.stderr.readline()
        assert "live 3D view" in line, line
        pub = s.declare_publisher(f"capsheet/{sheet}/estimate", congestion_control=zenoh.CongestionControl.BLOCK)
        huge_lattice = HEADER.pack(b"CEST", 1, 0, 5000, 5000, 25_000_000, 0, 1, 0.0, 0.0)
        for bad in (ONE_BY_ONE, huge_lattice, b"\xff" * 7, b"x" * (MAX_PAYLOAD_BYTES + 1)):
            for _ in range(3):  # the view keeps the newest of each sheet: give it time to take each one
                pub.put(bad)
                time.sleep(0.06)
        end = time.monotonic() + 3
        while time.monotonic() < end:
            pub.put(_estimate(3, 4))
            time.sleep(0.05)
        err = view.communicate(timeout=60)[1]
    finally:
        s.close()
        if view.poll() is None:
            view.kill()
    assert view.returncode == 0, err
    assert "Traceback" not in err, err
    assert "bad payload(s) refused" in err and " drawn" in err, err
    drawn = int(err.split(" drawn")[0].rsplit(", ", 1)[1].split()[0])
    assert drawn > 0, err


def _worker_snapshot(rows: int, cols: int) -> bytes:
    """A well-formed snapshot with gyroscopes, magnetometers and sample times: 42 bytes a link."""
    n = rows * (cols - 1) + cols * (rows - 1)
    snap = SimpleNamespace(readings=np.zeros((n, 3)), valid=np.ones(n, bool), status=np.zeros(n, np.uint8),
                           counter=1, timestamp=0.0, wall_time=time.time(), gyro=np.zeros((n, 3)),
                           mag=np.zeros((n, 3)), sample_time_s=np.zeros(n))
    return encode_snapshot(snap, rows, cols)


def _run_worker_flooded(payloads: list[bytes], sheet: str) -> tuple[dict, int, str]:
    """``capsheet estimate --subscribe --sheets '<sheet>*'`` while this test puts ``payloads`` on
    ``capsheet/<sheet>/snapshot`` (no host answers its info). Returns its JSON, peak RSS (MB) and stderr."""
    w = subprocess.Popen([sys.executable, "-c", MAXRSS, sys.executable, "-m", "host.cli", "estimate", "--subscribe",
                          "--sheets", sheet + "*", "--idle", "2", "--duration", "90", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
    s = open_session(None)
    try:
        assert "worker ready" in w.stderr.readline()
        pub = s.declare_publisher(f"capsheet/{sheet}/snapshot", congestion_control=zenoh.CongestionControl.BLOCK,
                                  reliability=zenoh.Reliability.RELIABLE)
        time.sleep(0.5)  # the worker's subscription reaches this session
        for p in payloads:
            pub.put(p)
        out, err = w.communicate(timeout=120)
    finally:
        s.close()
        if w.poll() is None:
            w.kill()
    rss_mb = int(err.rsplit("maxrss_kb ", 1)[1].split()[0]) / 1024
    return json.loads(out), rss_mb, err


def test_400_junk_payloads_of_1_mib_for_a_sheet_without_info_are_refused_and_memory_stays_bounded():
    rng = np.random.Generator(np.random.MT19937(49))
    junk = [rng.integers(0, 256, 1 << 20, dtype=np.uint8).tobytes() for _ in range(8)]
    sheet = _tag()
    doc, rss_mb, err = _run_worker_flooded([junk[k % 8] for k in range(400)], sheet)
    assert "Traceback" not in err, err
    assert doc["exit"] == 1
    (d,) = [d for d in doc["sheets"] if d["sheet"] == sheet]
    assert d["bad_payloads"] + d.get("dropped_queue_full", 0) == 400 and d["bad_payloads"] > 0, d
    assert rss_mb < 300, f"worker peak RSS {rss_mb:.0f} MB"  # was 627 MB when pending was counted in payloads


def test_well_formed_snapshots_for_a_sheet_without_info_are_held_up_to_the_byte_cap():
    """~1 MB snapshots that decode (a 2x8322 sheet with every IMU field): held while the sheet's info
    is awaited, up to 64 MB; the rest dropped, counted; the worker's memory stays bounded."""
    one = _worker_snapshot(2, 8322)
    assert 1_000_000 < len(one) <= MAX_PAYLOAD_BYTES and decode_snapshot(one)["n"] == 24964
    sheet = _tag()
    doc, rss_mb, err = _run_worker_flooded([one] * 200, sheet)
    assert "Traceback" not in err, err
    (d,) = [d for d in doc["sheets"] if d["sheet"] == sheet]
    assert d["info"] is False and d["bad_payloads"] == 0
    held = d["received"] - d["dropped_waiting"]
    assert held * len(one) <= 64 << 20 < (held + 1) * len(one), d
    assert rss_mb < 300, f"worker peak RSS {rss_mb:.0f} MB"


def test_the_info_queryable_answers_the_same_whatever_the_query_carries():
    """The publisher's ``info`` queryable reads nothing of a query (no payload, no parameters, no
    attachment): a 1 MiB payload and odd parameters get the sheet's info, as a plain query does."""
    from host.publish.zenoh_pub import ZenohPublisher, decode_info
    from protocol.lattice import Lattice

    sheet = _tag()
    pub = ZenohPublisher(sheet, None, Lattice(3, 4), 0.01)
    s = open_session(None)
    try:
        answers = []
        for kwargs in ({}, {"payload": b"\xff" * (1 << 20), "attachment": b"x" * 100}):
            for _ in range(20):  # the queryable's declaration reaches this session
                got = [r.ok for r in s.get(f"capsheet/{sheet}/info?rows=1;x=" + "y" * 1000, timeout=1.0, **kwargs)
                       if r.ok is not None]
                if got:
                    break
            answers.append(decode_info(bytes(got[0].payload.to_bytes())))
        assert answers[0] == answers[1] and (answers[0]["rows"], answers[0]["cols"]) == (3, 4)
        assert pub.counts["info"] >= 2
    finally:
        s.close()
        pub.close()
