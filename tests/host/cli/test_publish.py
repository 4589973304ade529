"""``--publish zenoh``: ``capsheet host`` against ``capsheet virtual`` on a pty, a Zenoh
subscriber in another process (peer mode on loopback, no router) that decodes every message kind
from docs/distribution.md alone. Asserts what is delivered and decoded, never a rate. The subscriber
ends when the publisher has ended and what the test waits for has come (tests/host/cli/zenoh_subscriber.py's
stdin), not after a fixed time (it listened 9 s and 15 s, whatever came)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.host.cli.cli_runs import CLI, ENV, host

pytest.importorskip("zenoh")
SUB = Path(__file__).with_name("zenoh_subscriber.py")


def test_host_publishes_every_kind_and_answers_a_late_query(virtuals, tmp_path):  # noqa: F811
    sheet = f"test{abs(hash(str(tmp_path))) % 10**8}"  # this test's own keys on a shared machine
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(tmp_path / "s.csv"))
    sub = subprocess.Popen([sys.executable, str(SUB), sheet, "60", "3"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert sub.stdout.readline().strip() == "ready"
        out = host(*v.host_cmd, "--duration", "3", "--publish", "zenoh", "--sheet-name", sheet,
                   "--live-rate", "5", "-q")
        # what is asserted below came while the host ran (the info answered while it was up)
        got, err = sub.communicate("end\n", timeout=60)
    finally:
        if sub.poll() is None:
            sub.kill()
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    doc = json.loads(got.strip().splitlines()[-1])
    assert doc["bad"] == [], doc["bad"]
    # the host says how many it published; the subscriber got those it was there for (discovery
    # takes a moment): every published snapshot after the first it saw, none twice, in order
    pub = out.stderr.split("published ")[1]
    n_snap, n_est = int(pub.split(" snapshots")[0]), int(pub.split("snapshots, ")[1].split(" estimates")[0])
    counters = [s["counter"] for s in doc["snapshot"]]
    assert len(counters) >= 10 and counters == sorted(set(counters))
    assert counters[-1] - counters[0] + 1 == len(counters)  # none lost between the first and the last
    assert len(counters) <= n_snap
    for s in doc["snapshot"]:
        assert (s["rows"], s["cols"], s["n"]) == (3, 3, 12)
    assert all(s["valid"] == 12 for s in doc["snapshot"][1:])
    assert all(abs(s["norm"] - 9.81) < 0.5 for s in doc["snapshot"] if s["valid"])  # m/s²: about 1 g
    assert 3 <= len(doc["estimate"]) <= n_est
    for e in doc["estimate"]:
        assert (e["rows"], e["cols"]) == (3, 3) and abs(e["link_m"] - 0.01) < 0.001  # joints in metres, L = 1 cm
    assert any(e["std"] is not None for e in doc["estimate"])  # the uncertainty, once a second
    assert doc["health"] and doc["health"][-1]["sheet"] == sheet and doc["health"][-1]["links"] == 12
    info = doc["info"]
    assert info is not None and (info["rows"], info["cols"], info["links"]) == (3, 3, 12)
    assert info["keys"]["snapshot"] == f"capsheet/{sheet}/snapshot"
    uids = {ln.split(",")[0].lower().removeprefix("0x").lstrip("0")
            for ln in (tmp_path / "s.csv").read_text().splitlines()[1:]}
    assert {c["uid"].lower().removeprefix("0x").lstrip("0") for c in info["layout"]["chips"]} == uids
    assert len(info["calibration"]["links"]) == 12


@pytest.mark.parametrize("value", ["mqtt", "zenoh:localhost"])
def test_a_bad_publish_value_is_one_line(value, cli_here):
    """Through the entry point in this process (refused before the port is opened); the first value
    through a real process as well."""
    runs = [cli_here(["host", "--port", "/nonexistent", "--publish", value])]
    if value == "mqtt":
        out = subprocess.run(CLI + ["host", "--port", "/nonexistent", "--publish", value], capture_output=True,
                             text=True, timeout=60, env=ENV)
        runs.append((out.returncode, out.stdout, out.stderr))
    for code, _out, err in runs:
        assert code == 2 and "--publish" in err and "Traceback" not in err, err


def test_tactile_publishes_snapshots_estimates_and_contacts(tmp_path):
    """``capsheet tactile --publish zenoh`` (the virtual foam): every snapshot, every frame's estimate
    and its contacts (JSON on ``capsheet/<sheet>/contacts``, docs/distribution.md), decoded in another
    process. The scripted presses are a 2 N sphere and a 1.5 N flat punch (``--indenter
    sphere-punch``): both on the sheet at once carry about 3.5 N."""
    sheet = f"touch{abs(hash(str(tmp_path))) % 10**8}"
    sub = subprocess.Popen([sys.executable, str(SUB), sheet, "60", "100000"], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert sub.stdout.readline().strip() == "ready"
        out = subprocess.run(CLI + ["tactile", "--duration", "3", "--publish", "zenoh", "--sheet-name", sheet, "-q",
                                    "--out", str(tmp_path / "t.png")], capture_output=True, text=True, timeout=120,
                             env=ENV)
        # the last frame's snapshot, estimate and contacts (frame k is snapshot k, from 0): all it published
        n = re.search(r"published (\d+) snapshots", out.stderr)
        last = int(n[1]) - 1 if n else 0
        got, err = sub.communicate(f"until snapshot={last},estimate={last},contacts={last}\n" if n else "end\n",
                                   timeout=90)
    finally:
        if sub.poll() is None:
            sub.kill()
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert "Traceback" not in err, err
    m = re.search(r"published (\d+) snapshots, (\d+) estimates, (\d+) contact frames", out.stderr)
    assert m and int(m[1]) == int(m[2]) == int(m[3]) == 25, out.stderr  # 3 s at 8 snapshots/s, and the first
    doc = json.loads(got.strip().splitlines()[-1])
    assert doc["bad"] == [], doc["bad"]
    frames = [c["frame"] for c in doc["contacts"]]
    assert len(frames) >= 10 and frames == list(range(frames[0], frames[0] + len(frames)))  # in order, none lost
    counters = [s["counter"] for s in doc["snapshot"]]  # the virtual sheet's snapshot k is frame k
    assert counters == list(range(counters[0], counters[0] + len(counters))) and set(frames) <= set(counters)
    assert [e["counter"] for e in doc["estimate"]] == frames
    for s in doc["snapshot"]:
        assert (s["rows"], s["cols"], s["n"], s["valid"]) == (14, 14, 364, 364) and abs(s["norm"] - 9.81) < 0.5
    for e in doc["estimate"]:
        assert (e["rows"], e["cols"]) == (14, 14) and abs(e["link_m"] - 0.01) < 0.001
    for c in doc["contacts"]:
        assert c["sheet"] == sheet and abs(sum(x["force_n"] for x in c["contacts"]) - c["total_force_n"]) < 1e-9
        for x in c["contacts"]:
            assert x["force_n"] > 0 and x["depth_m"] > 0 and x["radius_m"] > 0 and len(x["position"]) == 3
            assert 0 <= x["index"][0] <= 13 and 0 <= x["index"][1] <= 13
    assert max(len(c["contacts"]) for c in doc["contacts"]) == 2
    assert abs(max(c["total_force_n"] for c in doc["contacts"]) - 3.5) < 0.9
    assert doc["contacts"][-1]["contacts"] == []  # both released by the end
