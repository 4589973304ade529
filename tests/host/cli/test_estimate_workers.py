"""``capsheet estimate --subscribe``: two sheets (``capsheet virtual`` on ptys, each
with ``capsheet host --publish zenoh --no-publish-estimates``), two workers sharing them by
``--worker 0/2`` and ``1/2``, and a subscriber in another process (tests/host/cli/estimate_checker.py:
zenoh and docs/distribution.md only) that checks every snapshot of each sheet gets exactly one
estimate, in order, decoded. All on loopback in Zenoh peer mode, no router. Asserts what is
delivered, never a rate. Also the worker's errors: an unknown sheet, no router, usage.

The waits are for what is waited for: once the hosts have ended, the subscriber is told how many
snapshots each published and ends when it has an estimate of every one (it waited 8 s without a
message before); workers that are not the one ending by ``--idle`` are then ended as an operator
would (SIGTERM: what they received is estimated before they leave). The hosts stream 2 s: the
counts asserted (20 snapshots or more a sheet) come in the first second at 30 Hz."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

from tests import zenoh_meeting
from tests.host.cli.cli_runs import CLI, DELIVERY, ENV, popen_host, wait_line

pytest.importorskip("zenoh")
CHECKER = Path(__file__).with_name("estimate_checker.py")
HOST_S = "2"  #: each host's run: >= 20 snapshots at 50 Hz (`DELIVERY`) with room to spare
# the hosts run at `DELIVERY`: with the sheet's 145 Hz and the helpers' 0.5 s, a loaded machine (load
# 15-28) left the sheet's answers late and the hosts below their --min-complete (exit 1; "late" 564-588)


def _checker(names: list[str]) -> subprocess.Popen:
    """tests/host/cli/estimate_checker.py on ``names``; ``_expect`` then ends it."""
    return subprocess.Popen([sys.executable, str(CHECKER), ",".join(names), "150", "8"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)


def _expect(checker: subprocess.Popen, counts: dict[str, int]) -> tuple[str, str]:
    """Tell the checker how many estimates each sheet is due (one per published snapshot) and
    return its output once it has them (or its idle end came first)."""
    line = "expect " + ",".join(f"{k}={n}" for k, n in counts.items()) + "\n"
    return checker.communicate(line, timeout=120)


def _published(err: str) -> int:
    """The snapshots a ``capsheet host --publish zenoh`` run says it published."""
    return int(err.split("published ")[1].split(" snapshots")[0])


def _two_names(tmp_path) -> list[str]:
    """Two sheet names of this test's own (a shared machine), ``<base>_<k>``, one per worker of two:
    CRC-32 of the name modulo 2 is 0 for the first, 1 for the second (the rule docs/distribution.md
    states). The workers take ``<base>_*`` only: other tests' sheets on this loopback are not theirs."""
    base = f"t{abs(hash(str(tmp_path))) % 10**6}"
    names = {}
    k = 0
    while len(names) < 2:
        name = f"{base}_{k}"
        names.setdefault(zlib.crc32(name.encode()) % 2, name)
        k += 1
    return [names[0], names[1]]


def _worker(*args: str) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["estimate", "--subscribe", *args, "--json"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)


def test_two_workers_estimate_every_snapshot_of_two_sheets_once_in_order(virtuals, tmp_path):  # noqa: F811
    names = _two_names(tmp_path)
    pattern = names[0].rsplit("_", 1)[0] + "_*"
    # the workers and the checker start while the sheets do (each waited for the one before)
    workers = [_worker("--sheets", pattern, "--worker", f"{k}/2", "--idle", "6", "--duration", "150") for k in range(2)]
    procs = list(workers)
    try:
        checker = _checker(names)
        procs.append(checker)
        vs = [virtuals("--lattice", "3x3", "--symlink", str(tmp_path / f"sheet{k}"), "--layout-out",
                       str(tmp_path / f"s{k}.csv")) for k in range(2)]
        for w in workers:
            wait_line(w, "worker ready", 60, [])
        assert checker.stdout.readline().strip() == "ready"
        hosts = [popen_host(*v.host_cmd, "--duration", HOST_S, *DELIVERY, "--publish", "zenoh", "--no-publish-estimates",
                            "--sheet-name", name, "-q") for v, name in zip(vs, names)]
        procs += hosts
        host_err = [h.communicate(timeout=120)[1] for h in hosts]
        for h, err in zip(hosts, host_err):
            assert h.returncode == 0 and "Traceback" not in err, err
        published = [_published(err) for err in host_err]
        got, cerr = _expect(checker, dict(zip(names, published)))
        for w in workers:  # each has published what the checker counted: ended as an operator would
            if w.poll() is None:
                w.send_signal(signal.SIGTERM)
        done = [w.communicate(timeout=120) for w in workers]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert all(", 0 estimates" in err for err in host_err)  # the hosts left the estimates to the workers
    docs = []
    for w, (out, err) in zip(workers, done):
        assert "Traceback" not in err, err
        assert w.returncode == 0, err
        docs.append(json.loads(out))
    # each worker took exactly its sheet, by the CRC-32 rule, and left the other one
    for k, doc in enumerate(docs):
        assert [s["sheet"] for s in doc["sheets"]] == [names[k]], doc
        assert names[1 - k] in doc["ignored"]
    checked = json.loads(got.strip().splitlines()[-1])
    assert checked["bad"] == []
    for k, name in enumerate(names):
        w = docs[k]["sheets"][0]
        # the worker was there before the host streamed: every published snapshot, none lost
        assert (w["lost"], w["gaps"], w["duplicates"], w["old"], w["bad_payloads"]) == (0, 0, 0, 0, 0)
        assert w["received"] == published[k] >= 20
        assert w["received"] == w["last_counter"] - w["first_counter"] + 1
        assert w["estimated"] + w["not_estimated"] == w["received"]
        snaps = [s["counter"] for s in checked["sheets"][name]["snapshot"]]
        ests = checked["sheets"][name]["estimate"]
        counters = [e["counter"] for e in ests]
        # exactly one estimate per snapshot, in the snapshots' order, each decoded
        assert counters == list(range(w["first_counter"], w["last_counter"] + 1))
        assert set(snaps) <= set(counters) and len(snaps) >= 20
        assert sum(e["estimated"] for e in ests) == w["estimated"] >= len(ests) - 3  # the first may be empty
        for e in ests:
            assert (e["rows"], e["cols"]) == (3, 3)
            if e["estimated"]:
                assert e["finite"] and abs(e["link_m"] - 0.01) < 0.001  # metres, L = 1 cm (the info's)
        assert f"sheet {name}: received {published[k]}" in done[k][1]  # the summary says it


def test_an_unknown_sheet_is_one_line_and_exit_1():
    out = subprocess.run(CLI + ["estimate", "--subscribe", "--sheets", "no_such_sheet_here", "--wait", "1.5"],
                         capture_output=True, text=True, timeout=60, env=ENV)
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    assert "unknown sheet no_such_sheet_here" in out.stderr and "capsheet/no_such_sheet_here/info" in out.stderr


def test_no_reachable_router_is_one_line_and_exit_1():
    # its endpoint alone: the worker's meeting point (applied last) would replace it
    out = subprocess.run(CLI + ["estimate", "--subscribe", "zenoh:tcp/127.0.0.1:1", "--duration", "1"],
                         capture_output=True, text=True, timeout=60, env=zenoh_meeting.without_meeting(ENV))
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    assert "cannot reach the Zenoh router at tcp/127.0.0.1:1" in out.stderr


def test_nothing_received_is_said_and_exit_1():
    # a pattern no sheet matches: a worker that took every sheet would estimate other tests' sheets
    # beside their own workers (their checkers would see two estimates per snapshot)
    out = subprocess.run(CLI + ["estimate", "--subscribe", "--sheets", "nobody_publishes_this_*", "--worker", "0/1",
                                "--duration", "1.5"], capture_output=True, text=True, timeout=60, env=ENV)
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    assert "received no snapshot from nobody_publishes_this_*" in out.stderr


@pytest.mark.parametrize("args, needle", [
    (["--subscribe", "ros2"], "--subscribe"),
    (["--subscribe", "zenoh:localhost"], "bad Zenoh endpoint"),
    (["--subscribe", "--worker", "2/2"], "--worker"),
    (["--subscribe", "--sheets", "a/b"], "bad sheet name"),
    (["--subscribe", "--sheets", "a", "--worker", "0/2"], "not in --worker 0/2's share"),  # crc32(b"a") % 2 == 1
    (["--subscribe", "--method", "paper"], "auto, global or fused"),
    (["--subscribe", "--out", "x.npz"], "--out is for a recording"),
    (["--worker", "0/2"], "--worker is for an estimate worker"),
    ([], "give a recording"),
])
def test_usage_errors_are_one_line_and_exit_2(args, needle, tmp_path, cli_here):
    """Through the entry point in this process (tests/host/cli/conftest.py); the first case through a
    real process as well."""
    runs = [cli_here(["estimate", *args], cwd=tmp_path)]
    if args == ["--subscribe", "ros2"]:
        out = subprocess.run(CLI + ["estimate", *args], capture_output=True, text=True, timeout=60, env=ENV,
                             cwd=tmp_path)
        runs.append((out.returncode, out.stdout, out.stderr))
    for code, _out, err in runs:
        assert code == 2 and needle in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1, err


def test_a_host_refuses_no_publish_estimates_without_zenoh(cli_here):
    """Through the entry point in this process: the host refuses before it opens the port (its
    bad values through a real process are tests/host/cli/test_host.py's)."""
    code, _out, err = cli_here(["host", "--port", "/nonexistent", "--no-publish-estimates"])
    assert code == 2 and "--no-publish-estimates is for --publish zenoh" in err, err


def test_a_6_axis_sheet_is_estimated_by_the_fused_estimator_in_a_worker(virtuals, tmp_path):  # noqa: F811
    """A carried-and-turned sheet of 6-axis chips: its snapshots carry the gyroscopes (flag bit 0) and
    the worker shapes every one with the fused estimator, in order. The worker ends by itself
    (``--idle``: 3 s after the last snapshot)."""
    name = f"imu{abs(hash(str(tmp_path))) % 10**6}"
    worker = _worker("--sheets", name, "--wait", "60", "--idle", "3", "--duration", "150")
    procs = [worker]
    try:
        checker = _checker([name])  # the worker and the checker start while the sheet does
        procs.append(checker)
        v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(tmp_path / "s.csv"),
                     "--sensors", "accel+gyro", "--shape", "carry", "--noise", "1")
        assert checker.stdout.readline().strip() == "ready"
        host = popen_host(*v.host_cmd, "--sensors", "accel+gyro", "--duration", HOST_S, *DELIVERY, "--publish", "zenoh",
                          "--no-publish-estimates", "--sheet-name", name, "-q")
        procs.append(host)
        _, host_err = host.communicate(timeout=120)
        assert host.returncode == 0, host_err
        got, _ = _expect(checker, {name: _published(host_err)})
        out, err = worker.communicate(timeout=120)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert worker.returncode == 0 and "Traceback" not in err, err
    w = json.loads(out)["sheets"][0]
    checked = json.loads(got.strip().splitlines()[-1])
    assert checked["bad"] == []
    snaps = checked["sheets"][name]["snapshot"]
    assert snaps and all(s["flags"] & 1 and s["flags"] & 4 for s in snaps)  # gyroscopes and sample times
    assert max(s["gyro_max"] for s in snaps) > 0.01  # rad/s: the sheet turns
    assert (w["lost"], w["gaps"]) == (0, 0) and w["received"] >= 20
    assert w["methods"] == {"fused": w["estimated"]} and w["estimated"] >= w["received"] - 3
    ests = checked["sheets"][name]["estimate"]
    assert [e["counter"] for e in ests] == list(range(w["first_counter"], w["last_counter"] + 1))
    for e in ests:
        if e["estimated"]:
            assert e["finite"] and abs(e["link_m"] - 0.01) < 0.001
    assert f"{w['estimated']} fused" in err


def test_a_host_started_again_is_a_restart_for_the_worker_not_lost_snapshots(virtuals, tmp_path):  # noqa: F811
    """The sheet's host runs, ends, and runs again: its SYNC counter starts again from 0. The worker
    takes the second run as a new sequence (one restart), loses nothing and estimates every snapshot."""
    import threading
    import time

    from host.publish.zenoh_session import open_session
    name = f"rs{abs(hash(str(tmp_path))) % 10**6}"
    # the worker ends by itself 30 s after the last snapshot (a gap between the runs shorter than that
    # on a loaded machine); once it has published an estimate of every snapshot the hosts published,
    # SIGTERM ends it sooner, as an operator would (what it received is estimated before it leaves)
    worker = _worker("--sheets", name, "--wait", "60", "--idle", "30", "--duration", "200")
    try:  # it starts while the sheet does
        v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(tmp_path / "s.csv"))
    except BaseException:
        worker.kill()
        raise
    # a default session: it meets the worker's where the hosts' and the worker's meet (a session of its
    # own scouting by multicast met none of them, and the test waited for the worker's idle end)
    session = open_session(None)
    estimates = [0]
    lock = threading.Lock()

    def on_estimate(_sample) -> None:
        with lock:
            estimates[0] += 1
    sub = session.declare_subscriber(f"capsheet/{name}/estimate", on_estimate)
    try:
        published = []
        for _ in range(2):
            h = popen_host(*v.host_cmd, "--duration", HOST_S, *DELIVERY, "--publish", "zenoh", "--no-publish-estimates",
                           "--sheet-name", name, "-q")
            _, err = h.communicate(timeout=120)
            assert h.returncode == 0, err
            published.append(_published(err))
        end = time.monotonic() + 60
        while worker.poll() is None and time.monotonic() < end:
            with lock:
                if estimates[0] >= sum(published):
                    break
            time.sleep(0.1)
        if worker.poll() is None:
            worker.send_signal(signal.SIGTERM)
        out, err = worker.communicate(timeout=120)
    finally:
        if worker.poll() is None:
            worker.kill()
        sub.undeclare()
        session.close()
    assert worker.returncode == 0 and "Traceback" not in err, err
    w = json.loads(out)["sheets"][0]
    assert w["restarts"] == 1 and (w["lost"], w["gaps"], w["old"], w["duplicates"]) == (0, 0, 0, 0), w
    assert w["received"] == sum(published) and w["estimated"] + w["not_estimated"] == w["received"]
    assert "counting restarted 1 time(s)" in err
