"""The live view with the client Lichtblick and the ws-protocol-era tools use: the npm package
``@foxglove/ws-protocol`` (its ``FoxgloveClient``, subprotocol ``foxglove.websocket.v1``) under node,
connected to ``capsheet``'s live server, checked on the channels it is advertised and the messages it
receives. foxglove-sdk alone refuses that subprotocol with HTTP 400 (host/publish/live.py).

node and the package are installed best effort (``.ci/run``: ``npm install --prefix .venv/node
@foxglove/ws-protocol@0.8.0 ws@8``); without them the test is SKIPPED with the reason.
``CAPSHEET_NODE_MODULES`` names another ``node_modules`` folder."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from protocol.lattice import Lattice

ROOT = Path(__file__).resolve().parents[3]
CLIENT_JS = Path(__file__).with_name("node") / "ws_protocol_client.js"
NODE_MODULES = Path(os.environ.get("CAPSHEET_NODE_MODULES", ROOT / ".venv" / "node" / "node_modules"))
TOPICS = ["/capsheet/estimate", "/sheet/scene", "/sheet/joints"]


def _node() -> str:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (the npm @foxglove/ws-protocol client runs under node)")
    if not (NODE_MODULES / "@foxglove" / "ws-protocol" / "package.json").is_file():
        pytest.skip(f"@foxglove/ws-protocol is not installed in {NODE_MODULES} (.ci/run installs it best effort: "
                    f"npm install --prefix .venv/node @foxglove/ws-protocol@0.8.0 ws@8)")
    return node


class _Est:
    def __init__(self, joints, valid):
        self.joints, self.valid, self.method, self.residual, self.iterations = joints, valid, "global", 0.0, 1


def test_the_npm_ws_protocol_client_receives_the_channels_and_the_estimates():
    node = _node()
    from host.record.recording import Recorder

    lat = Lattice(4, 5)
    rng = np.random.Generator(np.random.MT19937(11))
    valid = np.ones(lat.n_links, bool)
    sent: dict[int, np.ndarray] = {}
    rec = Recorder(None, lat, 0.01, live_port=0, colour_by="links")
    try:
        p = subprocess.Popen([node, str(CLIENT_JS), rec.live.url, json.dumps(TOPICS), "2", "60"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env=dict(os.environ, NODE_PATH=str(NODE_MODULES)))
        k = 0
        end = time.monotonic() + 90
        while p.poll() is None and time.monotonic() < end:  # publish until the client has enough
            J = rng.normal(size=(lat.rows, lat.cols, 3))
            sent[k] = J
            rec.estimate(_Est(J, valid), k, float(k), 1.7e9 + k)
            k += 1
            time.sleep(0.05)
        out, err = p.communicate(timeout=30)
    finally:
        rec.close()
    doc = json.loads(out.strip().splitlines()[-1])
    assert p.returncode == 0, (doc["errors"], err)
    assert doc["subprotocol"] == "foxglove.websocket.v1"  # answered in the name it offered
    assert doc["serverName"].startswith("capsheet")
    channels = {c["topic"]: c for c in doc["channels"]}
    assert channels["/sheet/scene"]["schemaName"] == "foxglove.SceneUpdate"
    assert channels["/sheet/scene"]["encoding"] == "protobuf"
    assert channels["/sheet/joints"]["schemaName"] == "foxglove.PointCloud"
    ch = channels["/capsheet/estimate"]
    assert (ch["encoding"], ch["schemaName"]) == ("protobuf", "capsheet.v2.Estimate")
    # decoded with the schema the server advertised to the npm client (a FileDescriptorSet, base64)
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"])).file:
        pool.Add(fd)
    Estimate = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"]))
    assert doc["messages"]["/capsheet/estimate"]
    for payload in doc["messages"]["/capsheet/estimate"]:
        est = Estimate.FromString(base64.b64decode(payload))
        J = np.array(est.joints, dtype=np.float32).reshape(lat.rows, lat.cols, 3)
        np.testing.assert_array_equal(J, sent[est.counter].astype(np.float32))
    clouds = [base64.b64decode(m) for m in doc["messages"]["/sheet/joints"]]
    assert all(any(s.astype("<f4").tobytes() in pc for s in sent.values()) for pc in clouds)
    assert all(len(base64.b64decode(m)) > lat.n_links * 2 * 12 for m in doc["messages"]["/sheet/scene"])


def test_the_npm_client_sees_a_moving_6_axis_sheet_live_with_its_gyroscopes(tmp_path):
    """``capsheet host --sensors accel+gyro --live`` on a carried-and-turned sheet: the npm client
    gets ``/sheet/imu`` (every link's gyroscope, from the chips) beside estimates made by the fused
    estimator whose shapes change as the sheet moves."""
    node = _node()
    from tests.host.test_matrix import Job

    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", "accel+gyro", "--rate", "100",
            "--duration", "30", "-q", "--live", "0", "--live-rate", "10"]
    job = Job("pty", tmp_path, "live-imu", args, ["--shape", "carry", "--sensors", "accel+gyro", "--noise", "1"])
    try:
        url = job.proc.wait_line("live 3D view on ", 120, stream="err").split(" on ", 1)[1].split()[0]
        topics = ["/sheet/imu", "/capsheet/estimate"]
        p = subprocess.run([node, str(CLIENT_JS), url, json.dumps(topics), "5", "60"], capture_output=True, text=True,
                           timeout=90, env=dict(os.environ, NODE_PATH=str(NODE_MODULES)))
    finally:
        job.proc.p.terminate()  # the host's --duration is a bound; the client has what it needs
        job.finish()
    doc = json.loads(p.stdout.strip().splitlines()[-1])
    assert p.returncode == 0, (doc["errors"], p.stderr)
    channels = {c["topic"]: c for c in doc["channels"]}
    assert (channels["/sheet/imu"]["encoding"], channels["/sheet/imu"]["schemaName"]) == ("json", "capsheet.Imu")
    imu = [json.loads(base64.b64decode(m)) for m in doc["messages"]["/sheet/imu"]]
    for m in imu:
        assert m["n_links"] == 12 and m["links_with_imu"] == 12 and len(m["gyro"]) == 36
        assert m["mag"] is None and m["method"] == "fused"
    # the sheet is carried and turned: its links rotate (the scene's rates are tens of °/s)
    assert max(m["gyro_max_dps"] for m in imu) > 1.0
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    ch = channels["/capsheet/estimate"]
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"])).file:
        pool.Add(fd)
    Estimate = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"]))
    ests = [Estimate.FromString(base64.b64decode(m)) for m in doc["messages"]["/capsheet/estimate"]]
    assert all(e.method == "fused" for e in ests)
    shapes = [np.array(e.joints).reshape(3, 3, 3) for e in ests]
    # the moving sheet's shape: successive estimates differ by more than noise would move them
    assert max(np.abs(s - shapes[0]).max() for s in shapes[1:]) > 1e-4
