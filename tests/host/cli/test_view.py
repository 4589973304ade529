"""``capsheet view --config robot.toml``: the robot file's checks (host.robot), and
two sheets' estimates published on Zenoh (peer mode on loopback) merged into one live scene, read
by the npm ``@foxglove/ws-protocol`` client (tests/host/node/ws_protocol_client.js, under node):
each sheet's transform from the file's pose on ``/tf``, each sheet's joints in its own frame."""

from __future__ import annotations

import base64
import json
import math
import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from host.publish.robot import load_robot, parse_robot
from tests.host.cli.cli_runs import CLI, ENV
from tests.host.publish.test_live_node import CLIENT_JS, NODE_MODULES, _node

GOOD = """
[view]
frame = "base_link"
rate = 10

[[sheet]]
name = "left"
translation = [0.1, -0.2, 0.3]
rotation = [0.0, 0.0, 0.0, 1.0]

[[sheet]]
name = "right"
translation = [-0.5, 0.25, 1.0]
rpy_deg = [30.0, 90.0, -45.0]
"""


def test_a_robot_file_gives_each_sheet_its_pose(tmp_path):
    f = tmp_path / "robot.toml"
    f.write_text(GOOD)
    r = load_robot(f)
    assert (r.frame, r.rate, r.port, r.endpoint) == ("base_link", 10.0, None, None)
    assert [p.name for p in r.sheets] == ["left", "right"]
    assert r.sheets[0].translation == (0.1, -0.2, 0.3) and r.sheets[0].rotation == (0.0, 0.0, 0.0, 1.0)
    # rpy in degrees about fixed x, y, z (ROS's RPY): scipy's extrinsic "xyz" is the same rotation
    want = Rotation.from_euler("xyz", [30.0, 90.0, -45.0], degrees=True).as_quat()  # x, y, z, w
    got = np.array(r.sheets[1].rotation)
    assert min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-12


#: the bad robot files refused through a real `capsheet view` (the first; the others through the
#: entry point in this process: the same loader, line and exit status, without an interpreter each)
BAD_IN_A_PROCESS = 1


@pytest.mark.parametrize("body, needle", [
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0]\nrotation = [0, 0, 0, 1]", "translation (metres) must be 3 finite"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 2]", "not a unit quaternion"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]", "give one of rotation"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]\nrpy_deg = [0, 0, 0]",
     "give one of rotation"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, 'x']\nrotation = [0, 0, 0, 1]", "3 finite numbers"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, nan]\nrotation = [0, 0, 0, 1]", "3 finite numbers"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]\ncolour = 'red'", "unknown key colour"),
    ("[view]\nzoom = 2\n[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]",
     "unknown key zoom in [view]"),
    ("[sheets]\nname = 'a'", "unknown key sheets"),
    ("[view]\nport = 70000\n[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]", "TCP port"),
    ("[[sheet]]\nname = 'a/b'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]", "must be a sheet name"),
    ("[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]\n"
     "[[sheet]]\nname = 'a'\ntranslation = [0, 0, 0]\nrotation = [0, 0, 0, 1]", "given twice"),
    ("[view]\nframe = 'w'", "no sheet"),
    ("[[sheet]\nname = 'a'", "not TOML"),
])
def test_a_bad_robot_file_is_one_line_naming_what_is_wrong(tmp_path, body, needle, request, cli_here):
    f = tmp_path / "robot.toml"
    f.write_text(body)
    with pytest.raises(ValueError, match=needle.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]")):
        load_robot(f)
    if request.node.callspec.indices["body"] < BAD_IN_A_PROCESS:
        out = subprocess.run(CLI + ["view", "--config", str(f)], capture_output=True, text=True, timeout=60, env=ENV)
        code, err = out.returncode, out.stderr
    else:
        code, _out, err = cli_here(["view", "--config", str(f)])
    assert code == 2 and needle in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1


def test_a_missing_robot_file_is_one_line(tmp_path, cli_here):
    code, _out, err = cli_here(["view", "--config", str(tmp_path / "nope.toml")])
    assert code == 2 and "nope.toml: no such file" in err and "Traceback" not in err


def test_parse_robot_defaults():
    r = parse_robot({"sheet": [{"name": "s", "translation": [1, 2, 3], "rpy_deg": [0, 0, 90]}]})
    assert r.frame == "world" and r.rate is None
    np.testing.assert_allclose(r.sheets[0].rotation, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)


# A publisher of two sheets' estimates, each a flat grid in its own plane, in another process.
PRODUCER = textwrap.dedent("""
    import sys, time, numpy as np, zenoh
    from types import SimpleNamespace
    from host.publish.zenoh_pub import encode_estimate, zenoh_config
    names = sys.argv[1].split(",")
    s = zenoh.open(zenoh_config(None))
    pubs = {n: s.declare_publisher(f"capsheet/{n}/estimate") for n in names}
    end = time.monotonic() + float(sys.argv[2])
    k = 0
    while time.monotonic() < end:
        for i, n in enumerate(names):
            r, c = (3, 4) if i == 0 else (5, 2)
            J = np.zeros((r, c, 3)); J[..., 0], J[..., 1] = np.meshgrid(np.arange(r) * 0.01, np.arange(c) * 0.01, indexing="ij")
            J[..., 2] = 0.001 * (i + 1)
            pubs[n].put(encode_estimate(SimpleNamespace(joints=J), k, float(k), time.time(), uncertainty=False))
        k += 1
        time.sleep(0.05)
    s.close()
""")


def _decoder(channel):
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def test_two_sheets_in_one_scene_each_at_its_pose_for_the_npm_client(tmp_path):
    node = _node()
    tag = abs(hash(str(tmp_path))) % 10**6
    names = [f"v{tag}_left", f"v{tag}_right"]
    f = tmp_path / "robot.toml"
    f.write_text(GOOD.replace('"left"', f'"{names[0]}"').replace('"right"', f'"{names[1]}"'))
    view = subprocess.Popen(CLI + ["view", "--config", str(f), "--port", "0", "--duration", "120"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    producer = subprocess.Popen([sys.executable, "-c", PRODUCER, ",".join(names), "120"], env=ENV,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = view.stderr.readline()
        assert "live 3D view on ws://" in line, line + view.stderr.read()
        url = line.split("live 3D view on ")[1].split()[0]
        topics = ["/tf", f"/{names[0]}/joints", f"/{names[1]}/joints", f"/{names[0]}/scene"]
        client = subprocess.run([node, str(CLIENT_JS), url, json.dumps(topics), "3", "90"], capture_output=True,
                                text=True, timeout=120, env=dict(os.environ, NODE_PATH=str(NODE_MODULES)))
    finally:
        producer.terminate()
        time.sleep(0.5)
        view.terminate()
        _, err = view.communicate(timeout=60)
        producer.wait(30)
    doc = json.loads(client.stdout.strip().splitlines()[-1])
    channels = {c["topic"]: c for c in doc["channels"]}
    assert client.returncode == 0, (doc["errors"], client.stderr, {t: len(m) for t, m in doc["messages"].items()},
                                    sorted(channels), err)
    assert view.returncode == 0 and "Traceback" not in err, err
    assert channels["/tf"]["schemaName"] == "foxglove.FrameTransform"
    Tf = _decoder(channels["/tf"])
    tfs = {}
    for m in doc["messages"]["/tf"]:
        t = Tf.FromString(base64.b64decode(m))
        tfs[t.child_frame_id] = t
    assert set(tfs) == set(names)
    poses = load_robot(f).sheets
    for p in poses:
        t = tfs[p.name]
        assert t.parent_frame_id == "base_link"
        assert [t.translation.x, t.translation.y, t.translation.z] == pytest.approx(p.translation, abs=1e-12)
        q = [t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w]
        assert q == pytest.approx(Rotation.from_quat(p.rotation).as_quat() * np.sign(q[3] * p.rotation[3] or 1),
                                  abs=1e-9)
    assert tfs[names[1]].rotation.y != 0  # the rpy sheet is turned
    Cloud = _decoder(channels[f"/{names[0]}/joints"])
    for k, (name, (r, c)) in enumerate(zip(names, [(3, 4), (5, 2)])):
        for m in doc["messages"][f"/{name}/joints"]:
            pc = Cloud.FromString(base64.b64decode(m))
            assert pc.frame_id == name  # drawn in the sheet's own frame, placed by /tf
            pts = np.frombuffer(pc.data, "<f4").reshape(-1, 3)
            assert pts.shape == (r * c, 3)
            np.testing.assert_allclose(pts[:, 2], 0.001 * (k + 1), rtol=1e-6)  # what the producer sent
            np.testing.assert_allclose(pts[c, 0], 0.01, rtol=1e-6)
    assert channels[f"/{names[0]}/scene"]["schemaName"] == "foxglove.SceneUpdate"
    for name in names:
        assert f"sheet {name}: " in err and " estimates received" in err


def test_the_documented_example_is_a_valid_robot():
    from pathlib import Path
    r = load_robot(Path(__file__).resolve().parents[3] / "docs" / "robot.toml")
    assert [p.name for p in r.sheets] == ["left_forearm", "right_forearm", "chest"] and r.frame == "base_link"
    want = Rotation.from_euler("xyz", [0.0, -90.0, 0.0], degrees=True).as_quat()
    np.testing.assert_allclose(np.abs(r.sheets[2].rotation), np.abs(want), atol=1e-12)


def test_each_sheets_channels_are_advertised_before_any_estimate(tmp_path):
    """The view makes its channels before its server starts (a channel made while a client is
    connected can stay silent for it: docs/recording.md), so a client that connects before any
    estimate sees every sheet's /scene and /joints at once."""
    node = _node()
    tag = abs(hash(str(tmp_path))) % 10**6
    names = [f"w{tag}_left", f"w{tag}_right"]
    f = tmp_path / "robot.toml"
    f.write_text(GOOD.replace('"left"', f'"{names[0]}"').replace('"right"', f'"{names[1]}"'))
    view = subprocess.Popen(CLI + ["view", "--config", str(f), "--port", "0", "--duration", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        line = view.stderr.readline()
        assert "live 3D view on ws://" in line, line + view.stderr.read()
        url = line.split("live 3D view on ")[1].split()[0]
        # no producer: no estimate comes; the client ends at its first /tf (or times out), and what
        # counts is what was advertised by then
        client = subprocess.run([node, str(CLIENT_JS), url, json.dumps(["/tf"]), "1", "4"], capture_output=True,
                                text=True, timeout=60, env=dict(os.environ, NODE_PATH=str(NODE_MODULES)))
    finally:
        view.terminate()
        view.communicate(timeout=60)
    doc = json.loads(client.stdout.strip().splitlines()[-1])
    advertised = {c["topic"] for c in doc["channels"]}
    want = {"/tf"} | {f"/{n}/{t}" for n in names for t in ("scene", "joints")}
    assert want <= advertised, (sorted(want - advertised), client.stderr)
