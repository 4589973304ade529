"""``--publish zenoh`` (issue 31): ``capsheet host`` against ``capsheet virtual`` on a pty, a Zenoh
subscriber in another process (peer mode on loopback, no router) that decodes every message kind
from docs/distribution.md alone. Asserts what is delivered and decoded, never a rate."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.host.cli.test_host import CLI, ENV, host, virtuals  # noqa: F401 -- the fixture

pytest.importorskip("zenoh")
SUB = Path(__file__).with_name("zenoh_subscriber.py")


def test_host_publishes_every_kind_and_answers_a_late_query(virtuals, tmp_path):  # noqa: F811
    sheet = f"test{abs(hash(str(tmp_path))) % 10**8}"  # this test's own keys on a shared machine
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(tmp_path / "s.csv"))
    sub = subprocess.Popen([sys.executable, str(SUB), sheet, "9", "3"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert sub.stdout.readline().strip() == "ready"
        out = host(*v.host_cmd, "--duration", "4", "--publish", "zenoh", "--sheet-name", sheet,
                   "--live-rate", "5", "-q")
        got, err = sub.communicate(timeout=60)
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
def test_a_bad_publish_value_is_one_line(value):
    out = subprocess.run(CLI + ["host", "--port", "/nonexistent", "--publish", value], capture_output=True,
                         text=True, timeout=60, env=ENV)
    assert out.returncode == 2 and "--publish" in out.stderr and "Traceback" not in out.stderr, out.stderr
