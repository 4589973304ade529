"""``capsheet host --reader-processes --estimate-process`` through the real CLI on
ptys: what is delivered, counted and recorded, never a rate (benchmarks/bench_live.py measures
the 64x64 sheet at 145 Hz)."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np

from tests.host.cli.cli_runs import drain, finish, host, host_here, host_json, popen_host, wait_line  # noqa: F401


def _children(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of ``pid``'s child processes, from /proc."""
    out = []
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            stat = open(f"/proc/{p}/stat").read()
            cmd = open(f"/proc/{p}/cmdline", "rb").read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append((int(p), cmd))
    return out


def test_reader_and_estimator_processes_deliver_and_estimate_every_snapshot(virtuals, tmp_path):
    """Two packed gateways read by a reader process each, estimates made in an estimator process:
    every chip found on its own port, one reader per port beside the host while it streams and
    none after it, every snapshot recorded, every snapshot that reached the estimates either
    estimated or counted as not made, and the recorded estimates the ones the estimator makes of
    the recorded snapshots in this process."""
    from host.analysis.estimator import estimate
    from host.record.recording import read

    lay, rec, link = tmp_path / "sheet.json", tmp_path / "run.mcap", tmp_path / "gw"
    v = virtuals("--lattice", "6x6", "--gateways", "2", "--packed", "--symlink", str(link), "--layout-out", str(lay))
    p = popen_host(*v.host_cmd, "--reader-processes", "--estimate-process", "--record", str(rec),
                   "--live-rate", "1000", "--duration", "4", "--json", "-q")
    err: list = []
    wait_line(p, "started on", 120, err)
    kids = _children(p.pid)
    readers = [pid for pid, cmd in kids if " -S -c " in cmd]
    estimators = [pid for pid, cmd in kids if "spawn_main" in cmd]
    out = finish(p, drain(p, err), timeout_s=120)
    assert p.returncode == 0, "".join(err)
    assert len(readers) == 2, kids  # one per --port
    assert len(estimators) == 1, kids
    for pid in readers + estimators:  # ended with the host
        assert not os.path.exists(f"/proc/{pid}") or "Z" in open(f"/proc/{pid}/stat").read().split()[2], pid
    doc = json.loads(out)
    s = doc["summary"]
    assert "60 chips found, 60 assigned, 60 configured" in "".join(err), "".join(err)
    assert sorted(c["bus"] for c in doc["chips"].values()) == [0] * 30 + [1] * 30
    assert not s["errors"] and s["stray_frames"] == 0, s
    e = s["estimates"]
    assert e["where"] == "process" and e["made"] >= 10, e
    # each snapshot the main thread took was estimated, found the estimator full, or was bad
    taken = s["snapshots"] - doc["aggregator"]["dropped"]
    assert e["made"] + e["not_made_busy"] + e["skipped_bad"] <= taken, (e, taken)
    assert s["recorded"]["snapshots"] == s["snapshots"]  # every snapshot in the file
    r = read(rec)
    assert len(r.counter) == s["snapshots"]
    est_counters = np.asarray(r.estimates["counter"])
    assert 1 <= len(est_counters) == s["recorded"]["estimates"] <= e["made"]
    by_counter = {int(c): i for i, c in enumerate(r.counter)}
    for j, c in enumerate(est_counters[:5]):
        i = by_counter[int(c)]
        valid = np.asarray(r.valid[i], dtype=bool)
        mine = estimate(np.asarray(r.readings[i], dtype=float), 6, 6, 0.01, valid=valid, bad_readings="mask")
        # float32 in the file; a warm start converges to the same shape within the solver's tolerance
        np.testing.assert_allclose(np.asarray(r.estimates["joints"][j]).reshape(6, 6, 3), mine.joints, atol=2e-4)


def test_a_port_back_under_reader_processes_is_reconnected(virtuals, tmp_path):
    """The sheet's port goes away under a reader process (its pty closes: the reader ends, the host
    reads end of file) and the same device comes back on the same path (the virtual sheet's outage
    takes the pty number back, as a USB adapter plugged in again keeps its number): the host
    reconnects through a new reader and every link streams again, as it does reading the port itself."""
    lay, port = tmp_path / "sheet.csv", tmp_path / "sheet"
    a = virtuals("--lattice", "4x4", "--symlink", str(port), "--layout-out", str(lay),
                 "--faults", "outage_at_s=8,outage_s=0.5")
    p = popen_host(*a.host_cmd, "--reader-processes", "--duration", "300", "--json", "-q")
    err: list = []
    wait_line(p, "started on", 60, err)
    assert not any("went away" in ln for ln in err), "the host started after the outage: the machine is too slow"
    wait_line(p, "went away", 60, err)
    wait_line(p, "is back", 60, err)
    time.sleep(2.0)
    readers = [pid for pid, cmd in _children(p.pid) if " -S -c " in cmd]
    p.send_signal(signal.SIGTERM)
    doc = json.loads(finish(p, drain(p, err)))
    s = doc["summary"]
    assert s["reconnects"] >= 1 and not s["not_a_sheet"] and not s["missing_links"], (s, "".join(err))
    assert len(readers) == 1, readers  # the old reader ended, one new one reads the port
    assert a.p.poll() is None


def test_reader_processes_need_a_port_with_a_file_descriptor():
    """``loop://`` (pyserial's loopback) has no file descriptor to hand a reader: exit 1, one line."""
    out = host("--port", "loop://", "--reader-processes", "--lattice", "3x3", "--auto-assign", "--duration", "1")
    assert out.returncode == 1 and "through a reader process" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr


def test_reader_processes_on_a_can_bus_is_a_usage_error(cli_here):
    """Refused before anything opens: through the entry point in this process (the refusal above
    runs through a real one)."""
    out = host_here(cli_here, "--can", "virtual:rp", "--reader-processes", "--lattice", "3x3", "--auto-assign",
                    "--duration", "1")
    assert out.returncode == 2 and "--reader-processes reads serial ports" in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr


def test_auto_assign_behind_packing_sync_source_gateways_places_each_chip_in_its_gateways_runs(virtuals):
    """The command ``capsheet virtual --gateways 2 --packed --rate 145`` prints (``--auto-assign
    --sync follow``): auto-assign in plain uid order put chips of one gateway on the other's links,
    so each SYNC brought those links twice (a SAMPLE, and INVALID in the other gateway's SNAPSHOT)
    — 28 of 60 chips' samples duplicated or late, 76.7 % valid. Each chip now takes a link of the
    runs its gateway announced: every link once per snapshot, all of them valid."""
    v = virtuals("--lattice", "6x6", "--gateways", "2", "--packed", "--rate", "145")
    assert "--auto-assign" in v.host_cmd and "--sync" in v.host_cmd and "follow" in v.host_cmd, v.host_cmd
    out, doc = host_json(*v.host_cmd, "--reader-processes", "--duration", "3")
    assert out.returncode == 0, out.stderr
    assert "60 chips found, 60 assigned, 60 configured" in out.stderr, out.stderr
    runs = {b: [range(a, z + 1) for a, z in g["links"]] for b, g in enumerate(doc["summary"]["gateways"])}
    assert [list(r) for r in runs.values()] == [[range(0, 30)], [range(30, 60)]], runs
    on = {int(link): c["bus"] for link, c in doc["chips"].items()}
    assert sorted(on) == list(range(60))
    assert all(any(link in r for r in runs[bus]) for link, bus in on.items()), on
    agg = doc["aggregator"]
    assert agg["duplicates"] == 0 and agg["stray"] == 0, agg
    # every link at most once per snapshot (a chip on another gateway's link came twice: a SAMPLE and
    # an INVALID record). Not "every sample valid": a link the virtual gateway did not hear within
    # its 10 ms (§13.2) is an INVALID record on a loaded machine — a timing figure, bench_live's.
    assert agg["emitted"] > 0 and agg["samples"] <= 60 * agg["emitted"], agg
    assert doc["summary"]["sync_mode"] == "follow"
