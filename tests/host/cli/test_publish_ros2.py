"""``--publish ros2`` and ``--record-ros2``: ``capsheet host`` against ``capsheet
virtual`` on a pty, a ROS 2 subscriber without ROS in another process (Zenoh peers on loopback, no
router; tests/host/cli/ros2_subscriber.py) that checks the key expressions, attachments and liveliness
tokens against rmw_zenoh's documented layout and decodes every message with rosbags; the MCAP read
back with rosbags. Asserts what is delivered and decoded, never a rate."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests import zenoh_meeting
from tests.host.cli.cli_runs import CLI, ENV

pytest.importorskip("zenoh")
rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_typestore, get_types_from_msg  # noqa: E402

SUB = Path(__file__).with_name("ros2_subscriber.py")
MSGS = Path(__file__).resolve().parents[3] / "msgs" / "capsheet_msgs" / "msg"
# rmw_zenoh docs/design.md, "Graph Cache"
NODE_TOKEN = r"^@ros2_lv/{d}/([0-9a-f]+)/(\d+)/\2/NN/%/%capsheet/{s}$"
PUB_TOKEN = (r"^@ros2_lv/{d}/([0-9a-f]+)/(\d+)/(\d+)/MP/%/%capsheet/{s}/(%[^/]+)/([a-z_]+::msg::dds_::[A-Za-z0-9]+_)"
             r"/(RIHS01_[0-9a-f]{{64}})/([^/]*)$")


def typestore():
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for f in sorted(MSGS.glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"capsheet_msgs/msg/{f.stem}"))
    ts.register(types)
    return ts


def _name(tmp_path) -> tuple[str, int]:
    h = abs(hash(str(tmp_path)))
    return f"t{h % 10**8}", 1 + h % 200  # this test's own sheet and ROS domain on a shared machine


def test_host_publishes_the_rmw_zenoh_layout_and_records_a_ros2_mcap(virtuals, tmp_path):  # noqa: F811
    sheet, domain = _name(tmp_path)
    mcap = tmp_path / "run.mcap"
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(tmp_path / "s.csv"))
    sub = subprocess.Popen([sys.executable, str(SUB), str(domain), sheet, "40", "3"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert sub.stdout.readline().strip() == "ready"
        out = subprocess.run(CLI + ["host", *v.host_cmd, "--rate", "30", "--deadline-ms", "500", "--duration", "4",
                                    "--publish", "ros2", "--sheet-name", sheet, "--record-ros2", str(mcap),
                                    "--live-rate", "5", "-q"],
                             capture_output=True, text=True, timeout=120, env=dict(ENV, ROS_DOMAIN_ID=str(domain)))
        got, err = sub.communicate(timeout=60)
    finally:
        if sub.poll() is None:
            sub.kill()
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert "Traceback" not in err, err
    doc = json.loads(got.strip().splitlines()[-1])
    assert doc["bad"] == [], doc["bad"]
    ns = f"/capsheet/{sheet}"
    m = re.search(r"(\d+) snapshots, (\d+) joints and surfaces, (\d+) contact frames, (\d+) diagnostics", out.stderr)
    n_snap, n_est, n_diag = int(m[1]), int(m[2]), int(m[4])

    # key expressions: <domain>/<topic>/<DDS type>/<RIHS01 of rosbags' store> (the subscriber checked
    # the hash against rosbags); the topics and types promised in docs/distribution.md
    ts = typestore()
    for topic, typ in ((f"{ns}/snapshot", "capsheet_msgs/msg/LatticeSnapshot"),
                       (f"{ns}/joints", "sensor_msgs/msg/PointCloud2"),
                       (f"{ns}/surface", "visualization_msgs/msg/Marker")):
        pkg, _, name = typ.split("/")
        assert doc["keys"][topic] == f"{domain}{topic}/{pkg}::msg::dds_::{name}_/{ts.hash_rihs01(typ)}"

    # every snapshot after the first seen, in order, none twice, none lost between (as point 1)
    snaps = doc["samples"][f"{ns}/snapshot"]
    counters = [s["counter"] for s in snaps]
    assert len(counters) >= 10 and counters == sorted(set(counters)) and len(counters) <= n_snap
    assert counters[-1] - counters[0] + 1 == len(counters)
    assert all((s["rows"], s["cols"], s["n"], s["frame_id"]) == (3, 3, 12, f"capsheet_{sheet}") for s in snaps)
    assert all(s["valid"] == 12 and abs(s["norm"] - 9.81) < 0.5 for s in snaps[1:])  # m/s²: about 1 g

    joints = doc["samples"][f"{ns}/joints"]
    assert 3 <= len(joints) <= n_est
    for j in joints:
        assert (j["height"], j["width"], j["point_step"], j["row_step"]) == (3, 3, 16, 48)
        assert j["fields"] == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("std", 12, 7, 1)] or \
            j["fields"] == [["x", 0, 7, 1], ["y", 4, 7, 1], ["z", 8, 7, 1], ["std", 12, 7, 1]]
        assert abs(j["link_m"] - 0.01) < 0.001 and j["is_dense"]  # joints in metres, L = 1 cm
    assert any(j["std"] is not None for j in joints)  # the uncertainty, about once a second
    surf = doc["samples"][f"{ns}/surface"]
    assert 3 <= len(surf) <= n_est
    for s in surf:  # TRIANGLE_LIST, ADD; 2 triangles per cell of the 3x3 joint grid
        assert (s["type"], s["action"], s["points"], s["frame_id"]) == (11, 0, 2 * 4 * 3, f"capsheet_{sheet}")
        assert 0.009 < s["edge_m_min"] and s["edge_m_max"] < 0.021  # a link, or a cell's diagonal (< 2 L)
    # the vertices are the joints of the cloud stamped alike; each cell (joints r*3+c) split in two
    cells = []
    for r in range(2):
        for c in range(2):
            a, b, cc, d = 3 * r + c, 3 * (r + 1) + c, 3 * r + c + 1, 3 * (r + 1) + c + 1
            cells += [sorted([a, b, cc]), sorted([b, d, cc])]
    tri = doc["surface_triangles"]
    assert len(tri) >= 3
    for t in tri:
        assert t["max_off_m"] < 1e-6 and t["triangles"] == sorted(cells)

    # the attachment (design.md, "Publishers"): sequence numbers 1, 2, ... per publisher (consecutive
    # where nothing was lost), a source timestamp in ns since the epoch, the publisher's GID = XXH3-128
    # of its liveliness token
    pub_tokens = [t for t in doc["tokens"] if "/MP/" in t and f"/{sheet}/" in t]
    for topic in (f"{ns}/snapshot", f"{ns}/joints", f"{ns}/surface"):
        a = doc["attachments"][topic]
        assert a["seq"] == sorted(set(a["seq"])) and a["seq"][-1] <= (n_snap if "snapshot" in topic else n_est)
        assert all(1.7e18 < t < 4e18 for t in a["stamps_ns"])
        token = next(t for t in pub_tokens if f"/{topic.replace('/', '%')}/" in t)
        assert a["gids"] == [doc["gid_of_token"][token]]
    assert counters[-1] - counters[0] == doc["attachments"][f"{ns}/snapshot"]["seq"][-1] - \
        doc["attachments"][f"{ns}/snapshot"]["seq"][0]
    diag = doc["diagnostics"]
    assert 1 <= len(diag) <= n_diag and diag[-1]["name"] == f"capsheet: {sheet}"
    for d in diag:  # docs/distribution.md: WARN when links are missing or < 99 % of snapshots were complete
        v = {k: json.loads(x) for k, x in d["values"].items() if k != "sync_mode"}
        assert d["level"] == (1 if v["missing_links"] or (v["snapshots"] and v["complete_snapshots_pct"] < 99) else 0)
    assert json.loads(diag[-1]["values"]["links"]) == 12 and json.loads(diag[-1]["values"]["snapshots"]) <= n_snap

    # liveliness tokens (design.md, "Graph Cache"): the node, then one per publisher, each withdrawn
    # when the host ends; a late graph query (liveliness get) finds them all
    node = [t for t in doc["tokens"] if re.match(NODE_TOKEN.format(d=domain, s=sheet), t)]
    assert len(node) == 1
    zid = re.match(NODE_TOKEN.format(d=domain, s=sheet), node[0])[1]
    seen = {}
    for t in pub_tokens:
        p = re.match(PUB_TOKEN.format(d=domain, s=sheet), t)
        assert p, t
        assert p[1] == zid and p[2] == re.match(NODE_TOKEN.format(d=domain, s=sheet), node[0])[2]
        seen[p[4].replace("%", "/")] = (p[5], p[6], p[7])
    assert set(seen) == {f"{ns}/snapshot", f"{ns}/joints", f"{ns}/surface", f"{ns}/contacts", f"{ns}/info",
                         "/diagnostics"}
    for topic, key in doc["keys"].items():  # the token names the same type and hash as the data key
        assert key.endswith(f"/{seen[topic][0]}/{seen[topic][1]}")
    # QoS: best effort (2), keep last 5 for the sensor data; reliable, keep last 10 for /diagnostics
    assert seen[f"{ns}/snapshot"][2] == "2::,5:,:,:,," and seen["/diagnostics"][2] == "::,10:,:,:,,"
    assert seen[f"{ns}/info"][2] == ":1:,1:,:,:,,"  # reliable, transient local, keep last 1 (as /tf_static)
    # the latched info: a subscriber that came late (an advanced subscriber asking for history, as
    # rmw_zenoh's transient-local subscription) got the newest, after bring-up: layout and calibration
    info = json.loads(doc["late_info"])
    assert (info["sheet"], info["rows"], info["cols"], info["links"]) == (sheet, 3, 3, 12)
    uids = {ln.split(",")[0].lower().removeprefix("0x").lstrip("0")
            for ln in (tmp_path / "s.csv").read_text().splitlines()[1:]}
    assert {c["uid"].lower().removeprefix("0x").lstrip("0") for c in info["layout"]["chips"]} == uids
    assert len(info["calibration"]["links"]) == 12 and info["topics"]["joints"]["name"] == f"{ns}/joints"
    assert set(node + pub_tokens) <= set(doc.get("tokens_queried", []))
    assert set(node + pub_tokens) <= set(doc["tokens_gone"])

    # the MCAP: ROS 2 profile, read back by rosbags, the same counts the host reported
    with Reader(mcap) as r:
        conns = {c.topic: c for c in r.connections}
        assert {t: c.msgtype for t, c in conns.items()} == {
            f"{ns}/snapshot": "capsheet_msgs/msg/LatticeSnapshot", f"{ns}/joints": "sensor_msgs/msg/PointCloud2",
            f"{ns}/surface": "visualization_msgs/msg/Marker", "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
            f"{ns}/info": "std_msgs/msg/String"}
        assert conns[f"{ns}/snapshot"].msgcount == n_snap and conns[f"{ns}/joints"].msgcount == n_est
        assert conns["/diagnostics"].msgcount == n_diag
        infos = [json.loads(ts.deserialize_cdr(raw, c.msgtype).data) for c, _, raw in r.messages([conns[f"{ns}/info"]])]
        assert [i["layout"] is None for i in infos] == [True, False]  # at start, then after bring-up
        rec = [ts.deserialize_cdr(raw, c.msgtype).counter for c, _, raw in r.messages([conns[f"{ns}/snapshot"]])]
    assert counters[0] in rec and rec[rec.index(counters[0]):][:len(counters)] == counters


def test_an_endpoint_is_connected_to_without_scouting(virtuals, tmp_path):  # noqa: F811
    """``--publish ros2:ENDPOINT``: the host connects to the locator given (here the subscriber's
    own, multicast scouting off on both sides: nothing else could have brought them together)."""
    import socket
    sheet, domain = _name(tmp_path)
    with socket.socket() as s:  # a free port (the subscriber listens on it)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    locator = f"tcp/127.0.0.1:{port}"
    v = virtuals("--lattice", "2x2", "--symlink", str(tmp_path / "sheet"))
    sub = subprocess.Popen([sys.executable, str(SUB), str(domain), sheet, "30", "2", locator],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert sub.stdout.readline().strip() == "ready"
        out = subprocess.run(CLI + ["host", *v.host_cmd, "--rate", "30", "--deadline-ms", "500", "--duration", "3",
                                    "--publish", f"ros2:{locator}", "--sheet-name", sheet, "--live-rate", "5", "-q"],
                             capture_output=True, text=True, timeout=120,  # its endpoint alone (tests/zenoh_meeting.py)
                             env=dict(zenoh_meeting.without_meeting(ENV), ROS_DOMAIN_ID=str(domain)))
        got, err = sub.communicate(timeout=60)
    finally:
        if sub.poll() is None:
            sub.kill()
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert locator in out.stderr
    doc = json.loads(got.strip().splitlines()[-1])
    assert doc["bad"] == [], doc["bad"]
    snaps = doc["samples"][f"/capsheet/{sheet}/snapshot"]
    assert len(snaps) >= 10 and all((s["rows"], s["cols"], s["n"]) == (2, 2, 4) for s in snaps)
    assert len(doc["samples"][f"/capsheet/{sheet}/joints"]) >= 2
    assert any(re.match(NODE_TOKEN.format(d=domain, s=sheet), t) for t in doc["tokens"])


def test_tactile_records_contacts_and_estimates_to_a_ros2_mcap(tmp_path):
    mcap = tmp_path / "touch.mcap"
    out = subprocess.run(CLI + ["tactile", "--duration", "1.5", "--record-ros2", str(mcap), "--sheet-name", "palm",
                                "-q"], capture_output=True, text=True, timeout=300, env=ENV)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    m = re.search(r"recorded to \S+ ROS 2 messages: \d+ snapshots, (\d+) joints and surfaces, (\d+) contact frames",
                  out.stderr)
    assert m and int(m[1]) == int(m[2]) > 0, out.stderr
    ts = typestore()
    with Reader(mcap) as r:
        conns = {c.topic: c for c in r.connections}
        assert conns["/capsheet/palm/contacts"].msgtype == "capsheet_msgs/msg/Contacts"
        frames = [ts.deserialize_cdr(raw, c.msgtype) for c, _, raw in r.messages([conns["/capsheet/palm/contacts"]])]
    assert [f.frame for f in frames] == list(range(len(frames))) and len(frames) == int(m[2])
    touched = [f for f in frames if f.contacts]
    assert touched  # the virtual foam scene presses the sheet
    for f in touched:
        assert abs(sum(c.force_n for c in f.contacts) - f.total_force_n) < 1e-6
        assert all(c.force_n > 0 and c.depth_m > 0 and c.radius_m > 0 and np.isfinite(c.position.z) for c in f.contacts)


@pytest.mark.parametrize("args, env, needle", [
    (["--publish", "ros2:garbage"], {}, "--publish"),
    (["--publish", "ros2:tcp/127.0.0.1"], {}, "--publish"),
    (["--publish", "ros3"], {}, "--publish"),
    (["--record-ros2", "run.bag"], {}, "--record-ros2"),
    (["--publish", "ros2", "--sheet-name", "left-arm"], {}, "not a ROS 2 name"),
    (["--publish", "ros2"], {"ROS_DOMAIN_ID": "abc"}, "ROS_DOMAIN_ID"),
])
@pytest.mark.parametrize("command", ["host", "demo", "tactile"])
def test_a_bad_ros2_value_is_one_line_and_exit_2(tmp_path, command, args, env, needle, cli_here, monkeypatch):
    """Through the entry point in this process (tests/host/cli/conftest.py); each command's first case
    through a real process as well."""
    # before anything starts: no port opened (host's is absent), no virtual sheet started (demo)
    port = ["--port", "/nonexistent"] if command == "host" else []
    argv = [command, *port, "--duration", "1", *args]
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    runs = [cli_here(argv, cwd=tmp_path, timeout_s=120)]
    if args == ["--publish", "ros2:garbage"]:
        out = subprocess.run(CLI + argv, capture_output=True, text=True, timeout=120, env=dict(ENV, **env),
                             cwd=tmp_path)
        runs.append((out.returncode, out.stdout, out.stderr))
    for code, _out, err in runs:
        assert code == 2 and needle in err and "Traceback" not in err, err
        assert err.count("\n") == 1 and err.startswith(f"capsheet {command}: "), err
        assert not list(tmp_path.iterdir())  # nothing written


def test_an_existing_ros2_recording_needs_overwrite(tmp_path):
    f = tmp_path / "run.mcap"
    f.write_bytes(b"keep")
    out = subprocess.run(CLI + ["host", "--port", "/nonexistent", "--record-ros2", str(f)], capture_output=True,
                         text=True, timeout=60, env=ENV)
    assert out.returncode == 2 and "--overwrite" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert f.read_bytes() == b"keep"


def test_demo_records_ros2_and_replay_converts_its_recording(tmp_path):
    """``demo --record --record-ros2`` and ``replay run.mcap --record-ros2``: a capsheet recording
    converted to ROS 2, the same snapshots (counter and readings) as the live one recorded."""
    run, live, conv = tmp_path / "run.mcap", tmp_path / "live.mcap", tmp_path / "conv.mcap"
    out = subprocess.run(CLI + ["demo", "--lattice", "3x3", "--duration", "2", "--rate", "30", "--min-complete", "0",
                                "--record", str(run), "--record-ros2", str(live), "--json"], capture_output=True,
                         text=True, timeout=300, env=ENV, cwd=tmp_path)
    # the demo's own targets (joint error, completeness) are not under test here: its recordings are
    assert out.returncode in (0, 1) and "Traceback" not in out.stderr, out.stderr
    assert "recorded to" in out.stderr and run.exists() and live.exists(), out.stderr
    out = subprocess.run(CLI + ["replay", str(run), "--speed", "max", "--record-ros2", str(conv), "-q"],
                         capture_output=True, text=True, timeout=300, env=ENV, cwd=tmp_path)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    ts = typestore()

    def snapshots(path):
        with Reader(path) as r:
            conns = [c for c in r.connections if c.topic == "/capsheet/sheet/snapshot"]
            msgs = [ts.deserialize_cdr(raw, c.msgtype) for c, _, raw in r.messages(conns)]
            joints = sum(c.msgcount for c in r.connections if c.topic == "/capsheet/sheet/joints")
        return msgs, joints

    a, a_joints = snapshots(live)
    b, b_joints = snapshots(conv)
    # a second reader, mcap-ros2-support (Foxglove's): it parses the ros2msg schema text itself
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    with open(live, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        seen = {}
        for schema, channel, _, msg in reader.iter_decoded_messages():
            seen.setdefault(channel.topic, []).append(msg)
        assert reader.get_header().profile == "ros2"
    assert [m.counter for m in seen["/capsheet/sheet/snapshot"]] == [m.counter for m in a]
    assert len(seen["/capsheet/sheet/surface"]) == a_joints
    assert all(m.type == 11 and len(m.points) == 24 for m in seen["/capsheet/sheet/surface"])
    assert json.loads(seen["/capsheet/sheet/info"][-1].data)["layout"] is not None
    assert len(a) >= 50 and [m.counter for m in a] == [m.counter for m in b]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.specific_force, y.specific_force)
        np.testing.assert_array_equal(x.valid, y.valid)
    # replay estimates every snapshot with a valid link (a loaded demo can record an empty one:
    # its SYNC went unanswered in time; replay has nothing to estimate there)
    assert 0 < a_joints and b_joints == sum(1 for m in b if np.any(m.valid))


def _tilt_deg(q, f) -> float:
    """The angle between the specific force turned into the fixed frame by the orientation ``q``
    (x, y, z, w) and +z: REP 145's convention, +g up at rest."""
    x, y, z, w = q
    Rm = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                   [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                   [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    v = Rm @ np.asarray(f)
    return float(np.degrees(np.arccos(v[2] / np.linalg.norm(v))))


def test_a_9_axis_demo_publishes_and_records_an_imu_per_link(tmp_path):
    """``capsheet demo --sensors accel+gyro+mag --publish ros2 --record-ros2``: one ``sensor_msgs/Imu``
    topic and one ``MagneticField`` topic per link (docs/distribution.md), decoded by rosbags in
    another process and in the MCAP; the fused orientations turn each link's accelerometer to +z
    (REP 145: orientation sensor -> fixed frame, +g up at rest; within the estimator's error); ``capsheet replay --no-estimate``
    converts the demo's recording with the same readings and no orientation."""
    sheet, domain = _name(tmp_path)
    live, run, conv = tmp_path / "live.mcap", tmp_path / "run.mcap", tmp_path / "conv.mcap"
    sub = subprocess.Popen([sys.executable, str(SUB), str(domain), sheet, "60", "3"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert sub.stdout.readline().strip() == "ready"
        out = subprocess.run(CLI + ["demo", "--lattice", "3x3", "--duration", "3", "--rate", "30", "--min-complete", "0",
                                    "--sensors", "accel+gyro+mag", "--publish", "ros2", "--sheet-name", sheet,
                                    "--record-ros2", str(live), "--record", str(run), "--out", str(tmp_path / "d.png")],
                             capture_output=True, text=True, timeout=300, env=dict(ENV, ROS_DOMAIN_ID=str(domain)))
        got, err = sub.communicate(timeout=90)
    finally:
        if sub.poll() is None:
            sub.kill()
    # the demo's own targets are not under test here: what it published and recorded is
    assert out.returncode in (0, 1) and "Traceback" not in out.stderr, out.stderr
    assert "Traceback" not in err, err
    m = re.search(r"(\d+) snapshots, .* (\d+) link IMU and (\d+) magnetic field messages", out.stderr)
    assert m, out.stderr
    n_snap, n_imu, n_mag = int(m[1]), int(m[2]), int(m[3])
    assert n_imu == n_mag and 0 < n_imu <= 12 * n_snap
    doc = json.loads(got.strip().splitlines()[-1])
    assert doc["bad"] == [], doc["bad"]
    ts = typestore()
    ns = f"/capsheet/{sheet}"
    links = [f"link_{k:03d}" for k in range(12)]
    for ln in links:
        for topic, typ, dds in ((f"{ns}/{ln}/imu/data", "sensor_msgs/msg/Imu", "Imu_"),
                                (f"{ns}/{ln}/imu/mag", "sensor_msgs/msg/MagneticField", "MagneticField_")):
            assert doc["keys"][topic] == f"{domain}{topic}/sensor_msgs::msg::dds_::{dds}/{ts.hash_rihs01(typ)}"
            token = [t for t in doc["tokens"] if f"/{topic.replace('/', '%')}/" in t]
            assert len(token) == 1 and token[0].endswith(f"/sensor_msgs::msg::dds_::{dds}/{ts.hash_rihs01(typ)}"
                                                         f"/2::,5:,:,:,,"), token  # best effort, keep last 5
        imu = doc["samples"][f"{ns}/{ln}/imu/data"]
        mag = {s["stamp"]: s for s in doc["samples"][f"{ns}/{ln}/imu/mag"]}
        assert len(imu) >= 10
        for s in imu:
            assert s["frame_id"] == f"capsheet_{sheet}_{ln}"
            assert abs(np.linalg.norm(s["f"]) - 9.81) < 2.0 and _tilt_deg(s["q"], s["f"]) < 20.0
            assert abs(np.linalg.norm(s["q"]) - 1) < 1e-9 and s["ocov"][0] > 0
            # docs/distribution.md: ICM-42688-P 2.8 mdps/√Hz over 145/2 Hz (DS-000347, Table 1) and 1 % g
            # per axis, LIS3MDL 0.4 µT
            gyro_rps = np.radians(2.8e-3 * np.sqrt(145.0 / 2.0))
            np.testing.assert_allclose(s["wcov"], np.diag([gyro_rps ** 2] * 3).ravel(), rtol=1e-9)
            np.testing.assert_allclose(s["fcov"], np.diag([0.0981 ** 2] * 3).ravel(), rtol=2e-3)
            mg = mag[s["stamp"]]  # the same sample: the same stamp
            assert mg["frame_id"] == s["frame_id"] and 5e-6 < np.linalg.norm(mg["m"]) < 2e-4  # tesla
            np.testing.assert_allclose(mg["cov"], np.diag([0.4e-6 ** 2] * 3).ravel())
        # the estimator's tilt error on a moving sheet (docs/estimator.md §8: about a degree), with room
        # for its first snapshots; a rotation the wrong way round or a quaternion in w, x, y, z order is
        # tens of degrees off
        tilts = [_tilt_deg(s["q"], s["f"]) for s in imu]
        assert np.median(tilts) < 3.0 and np.percentile(tilts, 90) < 8.0, tilts
        stamps = [s["stamp"] for s in imu]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        assert doc["attachments"][f"{ns}/{ln}/imu/data"]["seq"] == sorted(set(
            doc["attachments"][f"{ns}/{ln}/imu/data"]["seq"]))

    def link_imu(path):
        with Reader(path) as r:
            conns = {c.topic: c for c in r.connections if "/imu/" in c.topic}
            return {t: [ts.deserialize_cdr(raw, c.msgtype) for c, _, raw in r.messages([c])] for t, c in conns.items()}

    rec = link_imu(live)
    assert set(rec) == {f"{ns}/{ln}/imu/{k}" for ln in links for k in ("data", "mag")}
    assert sum(len(v) for t, v in rec.items() if t.endswith("data")) == n_imu
    for ln in links:
        topic = f"{ns}/{ln}/imu/data"
        recorded = [x.header.stamp.sec + 1e-9 * x.header.stamp.nanosec for x in rec[topic]]
        published = [s["stamp"] for s in doc["samples"][topic]]  # what was published was recorded
        assert set(published) <= set(recorded) and len(published) >= 0.5 * len(recorded)
        tilts = [_tilt_deg([x.orientation.x, x.orientation.y, x.orientation.z, x.orientation.w],
                           [x.linear_acceleration.x, x.linear_acceleration.y, x.linear_acceleration.z])
                 for x in rec[topic]]
        assert np.median(tilts) < 3.0 and max(tilts) < 20.0

    out = subprocess.run(CLI + ["replay", str(run), "--speed", "max", "--no-estimate", "--record-ros2", str(conv),
                                "--sheet-name", sheet, "-q"], capture_output=True, text=True, timeout=300, env=ENV)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    conv_imu = link_imu(conv)
    assert set(conv_imu) == set(rec)
    for topic, msgs in conv_imu.items():
        if topic.endswith("/data"):
            assert all(x.orientation_covariance[0] == -1.0 for x in msgs)  # no estimator: no orientation
        # the same samples (their stamps to a microsecond: the recording keeps sample times as float32),
        # the same readings
        field = "angular_velocity" if topic.endswith("/data") else "magnetic_field"

        def stamp(x):
            return x.header.stamp.sec + 1e-9 * x.header.stamp.nanosec
        tb = np.array([stamp(x) for x in msgs])
        matched = 0
        for x in rec[topic]:
            i = int(np.argmin(np.abs(tb - stamp(x))))
            if abs(tb[i] - stamp(x)) < 2e-6:
                matched += 1
                va, vb = getattr(x, field), getattr(msgs[i], field)
                np.testing.assert_allclose([vb.x, vb.y, vb.z], [va.x, va.y, va.z], rtol=1e-6, atol=1e-12)
        # every live sample is in the conversion (the recording also has the SYNCs the demo's loop did
        # not get to before its end)
        assert matched == len(rec[topic]) and len(msgs) >= len(rec[topic]), (matched, len(rec[topic]), len(msgs))
