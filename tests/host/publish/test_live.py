"""The live 3D view (host/publish/live.py): a headless Foxglove WebSocket client (``websockets``, subprotocol
``foxglove.sdk.v1`` as the Foxglove app offers it, or ``foxglove.websocket.v1`` as Lichtblick and the
``@foxglove/ws-protocol`` client do) connects to the server on localhost, subscribes, and decodes the
estimates and the scene it is sent; colours by error, displacement and link state. The real npm
client under node is driven in test_live_node.py."""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import struct

import numpy as np
import pytest

websockets = pytest.importorskip("websockets")

from host.publish.live import ERROR_FULL_SCALE_PCT, SceneChannels, colours  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"
V1 = "foxglove.websocket.v1"


class Est:
    def __init__(self, joints, valid):
        self.joints, self.valid, self.method, self.residual, self.iterations = joints, valid, "global", 0.0, 1


class Snap:
    def __init__(self, counter, valid):
        self.counter, self.timestamp, self.wall_time, self.valid = counter, float(counter), 1.7e9 + counter, valid


async def _client(url: str, topics: list[str], publish, want: int, max_rounds: int = 200,
                  subprotocol: str = SUBPROTOCOL):
    """Connect offering ``subprotocol``, subscribe to ``topics``, call ``publish(k)`` until ``want``
    messages per topic came. Returns (advertised channels by topic, {topic: [payload bytes]})."""
    async with websockets.connect(url, subprotocols=[subprotocol], max_size=None) as ws:
        assert ws.subprotocol == subprotocol  # answered in the name it asked for
        info = json.loads(await asyncio.wait_for(ws.recv(), 10))
        assert info["op"] == "serverInfo"
        channels: dict[str, dict] = {}
        for k in range(max_rounds):  # a channel made on first use is advertised when first used
            if all(t in channels for t in topics):
                break
            try:
                msg = json.loads(await asyncio.wait_for(ws.recv(), 0.5))
            except asyncio.TimeoutError:
                await asyncio.to_thread(publish, 1000 + k)
                continue
            if msg["op"] == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
        assert all(t in channels for t in topics), sorted(channels)
        sub_of = {k + 1: t for k, t in enumerate(topics)}
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": sid, "channelId": channels[t]["id"]} for sid, t in sub_of.items()]}))
        got: dict[str, list] = {t: [] for t in topics}
        for k in range(max_rounds):  # bounded: a round publishes once and waits for what comes
            await asyncio.to_thread(publish, k)
            try:
                while True:
                    m = await asyncio.wait_for(ws.recv(), 0.5)
                    if isinstance(m, bytes) and m[0] == 0x01:
                        sid, _ts = struct.unpack_from("<IQ", m, 1)
                        got[sub_of[sid]].append(m[13:])
            except asyncio.TimeoutError:
                pass
            if all(len(v) >= want for v in got.values()):
                break
        return channels, got


@pytest.mark.parametrize("subprotocol", [SUBPROTOCOL, V1])
def test_a_foxglove_client_subscribes_and_decodes_the_estimates_joints(subprotocol):
    from host.record.recording import Recorder

    lat = Lattice(4, 5)
    rng = np.random.Generator(np.random.MT19937(7))
    sent: dict[int, np.ndarray] = {}
    rec = Recorder(None, lat, 0.01, live_port=0, colour_by="links")
    try:
        valid = np.ones(lat.n_links, bool)
        valid[3] = False

        def publish(k):
            J = rng.normal(size=(4, 5, 3))
            sent[k] = J
            rec.estimate(Est(J, valid), k, float(k), 1.7e9 + k)

        channels, got = asyncio.run(_client(rec.live.url, ["/capsheet/estimate", "/sheet/scene", "/sheet/joints"],
                                            publish, want=2, subprotocol=subprotocol))
    finally:
        rec.close()
    assert channels["/sheet/scene"]["schemaName"] == "foxglove.SceneUpdate"
    assert channels["/sheet/scene"]["encoding"] == "protobuf"
    assert channels["/sheet/joints"]["schemaName"] == "foxglove.PointCloud"
    est = channels["/capsheet/estimate"]
    assert (est["encoding"], est["schemaName"]) == ("protobuf", "capsheet.v2.Estimate")
    # decoded with the schema the server advertised (a FileDescriptorSet, base64), not capsheet's code
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(est["schema"])).file:
        pool.Add(fd)
    Estimate = message_factory.GetMessageClass(pool.FindMessageTypeByName(est["schemaName"]))
    assert got["/capsheet/estimate"]
    for payload in got["/capsheet/estimate"]:
        doc = Estimate.FromString(payload)
        J = np.array(doc.joints, dtype=np.float32).reshape(4, 5, 3)
        np.testing.assert_array_equal(J, sent[doc.counter].astype(np.float32))
    # the point cloud carries the joints as packed float32 x, y, z: find them in the protobuf bytes
    pc = got["/sheet/joints"][0]
    assert any(sent[k].astype("<f4").tobytes() in pc for k in sent)
    assert all(len(p) > 20 * 2 * 12 for p in got["/sheet/scene"])  # 2 points per link, 3 floats each


def test_link_colours_by_state_error_and_displacement():
    lat = Lattice(3, 3)
    import foxglove
    sc = SceneChannels(foxglove.Context(), lat, colour_by="links")
    valid = np.ones(lat.n_links, bool)
    valid[[2, 5]] = False
    c = sc.link_colours(valid)
    assert c.shape == (2 * lat.n_links, 4)
    red = np.array([0.9, 0.1, 0.1, 1.0])
    missing = np.flatnonzero(np.all(np.isclose(c.reshape(lat.n_links, 2, 4), red), axis=(1, 2)))
    assert missing.tolist() == [2, 5]  # missing links shown, in red
    sc_e = SceneChannels(foxglove.Context(), lat, colour_by="error")
    err = np.zeros((3, 3))
    err[2, 2] = 2 * ERROR_FULL_SCALE_PCT  # one joint far off: its links' far end is full red
    ce = sc_e.link_colours(np.ones(lat.n_links, bool), error=err)
    ends = np.asarray(lat.endpoints)
    far = np.flatnonzero(ends[:, 1] == 8)
    np.testing.assert_allclose(ce[2 * far + 1, :3], [[0.9, 0.15, 0.1]] * len(far))  # full scale: red
    np.testing.assert_allclose(ce[2 * far, :3], [[0.1, 0.2, 0.9]] * len(far))  # no error: blue
    np.testing.assert_allclose(colours(np.array([np.nan]), 1.0)[0], [0.5, 0.5, 0.5, 1.0])
    sc_d = SceneChannels(foxglove.Context(), lat, colour_by="displacement")
    disp = np.zeros((3, 3))
    disp[1, 1] = -0.004  # a press: displacement magnitude is what is coloured
    cd = sc_d.link_colours(np.ones(lat.n_links, bool), displacement=disp)
    touching = np.flatnonzero((ends == 4).any(axis=1))
    assert not np.allclose(cd[2 * touching].sum(), cd[2 * np.setdiff1d(np.arange(lat.n_links), touching)].sum())
    with pytest.raises(ValueError, match="Invalid colour_by: 'rainbow'"):
        SceneChannels(foxglove.Context(), lat, colour_by="rainbow")


def test_contacts_are_sent_as_markers_with_their_force():
    from host.record.recording import Recorder

    lat = Lattice(3, 3)
    rec = Recorder(None, lat, 0.01, live_port=0)
    try:
        def publish(k):
            rec.contacts(k, float(k), [{"id": 4, "index": [1.0, 1.0], "position": [0.01, 0.01, -0.002],
                                        "force_n": 2.5 + k, "radius_m": 0.006}])

        _, got = asyncio.run(_client(rec.live.url, ["/sheet/scene", "/capsheet/contacts"], publish, want=1))
    finally:
        rec.close()
    doc = json.loads(got["/capsheet/contacts"][0])
    k = doc["counter"]
    assert doc["contacts"][0]["force_n"] == 2.5 + k
    scene = b"".join(got["/sheet/scene"])
    assert b"contacts" in scene and f"#4 {2.5 + k:.2f} N".encode() in scene


def test_the_live_flag_wires_a_server_into_a_session(capsys):
    from host.cli.record_args import SessionOutputs

    args = argparse.Namespace(record=None, live=0, live_rate=1000.0)
    out = SessionOutputs(args, Lattice(3, 3), 0.01, mode="host")
    try:
        assert out.recorder.live is not None and out.recorder.path is None
        assert f"live 3D view on {out.recorder.live.url}" in capsys.readouterr().err
    finally:
        out.close()


def test_a_port_in_use_is_one_clear_error():
    import socket
    import foxglove
    from host.publish.live import LiveServer

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    try:
        with pytest.raises(OSError, match=f"Cannot start the live view on 127.0.0.1:{s.getsockname()[1]}"):
            LiveServer(foxglove.Context(), port=s.getsockname()[1])
    finally:
        s.close()


def test_a_session_estimates_past_a_dead_chip_and_counts_what_it_cannot(tmp_path, capsys):
    """A chip reading (0, 0, 0) with status OK must not end a recording session: it is masked out of
    the estimate; a snapshot with nothing estimable is counted and reported, not raised."""
    from host.snapshots.snapshot import LatticeSnapshot
    from host.cli.record_args import SessionOutputs
    from host.record.recording import read_recording
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.shapes import make_sheet

    lat = Lattice(4, 4)
    r = ideal_readings(make_sheet("cylinder", 4, 4, 0.01))
    r[3] = 0.0  # the dead chip

    def snap(k, readings, valid):
        return LatticeSnapshot(k, float(k), float(k), readings, valid, np.zeros(lat.n_links, np.uint8),
                               bool(valid.all()), 0.0)

    args = argparse.Namespace(record=str(tmp_path / "run.mcap"), live=None, live_rate=1e9)
    out = SessionOutputs(args, lat, 0.01, mode="host")
    est = out.snapshot(snap(0, r, np.ones(lat.n_links, bool)), force=True)
    assert est is not None and np.all(np.isfinite(est.joints))
    only_dead = np.zeros(lat.n_links, bool)
    only_dead[3] = True
    assert out.snapshot(snap(1, r, only_dead), force=True) is None
    out.close()
    assert "1 snapshots could not be estimated" in capsys.readouterr().err
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) == 2


def test_a_live_session_records_the_sampled_uncertainty_at_most_once_a_second(tmp_path):
    """yaw_std costs tens of estimates: recorded for the first estimate, not for one 1 ms later;
    the second estimate's lazy property is never computed for the recording."""
    from host.snapshots.snapshot import LatticeSnapshot
    from host.analysis.estimator import estimate
    from host.cli.record_args import SessionOutputs
    from host.record.recording import read_recording
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.shapes import make_sheet

    lat = Lattice(4, 4)
    r = ideal_readings(make_sheet("cylinder", 4, 4, 0.01))
    ok = np.ones(lat.n_links, bool)
    args = argparse.Namespace(record=str(tmp_path / "run.mcap"), live=None, live_rate=1e9)
    out = SessionOutputs(args, lat, 0.01, mode="host")
    snaps = [LatticeSnapshot(k, float(k), float(k), r, ok, np.zeros(lat.n_links, np.uint8), True, 0.0)
             for k in range(2)]
    first = out.snapshot(snaps[0])
    second = out.snapshot(snaps[1])
    assert "yaw_std" not in second.__dict__  # not computed
    out.close()
    rec = read_recording(tmp_path / "run.mcap")
    ys = rec.estimates["yaw_std"]
    assert ys.shape == (2, lat.n_links)
    np.testing.assert_array_equal(ys[0], first.yaw_std.astype(np.float32))
    assert np.isnan(ys[1]).all()
    np.testing.assert_array_equal(ys[0], estimate(r, 4, 4, 0.01).yaw_std.astype(np.float32))


@pytest.mark.parametrize("offer, upstream, answer", [
    ("foxglove.websocket.v1", "foxglove.sdk.v1", "foxglove.websocket.v1"),  # Lichtblick, @foxglove/ws-protocol
    ("foxglove.sdk.v1", "foxglove.sdk.v1", None),  # the Foxglove app: unchanged
    ("foxglove.websocket.v1, foxglove.sdk.v1", "foxglove.websocket.v1, foxglove.sdk.v1", None),
    ("graphql-ws", "graphql-ws", None),  # nothing we serve: the SDK answers it (400)
])
def test_the_handshake_is_translated_only_for_the_older_name(offer, upstream, answer):
    from host.publish.live import rewrite_request, rewrite_response

    head = (b"GET / HTTP/1.1\r\nHost: localhost:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"sec-websocket-protocol: " + offer.encode() + b"\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n")
    up, got = rewrite_request(head)
    assert got == answer
    lines = up.split(b"\r\n")
    assert lines[0] == b"GET / HTTP/1.1" and up.endswith(b"\r\n\r\n")
    protos = [ln.split(b":", 1)[1].strip().decode() for ln in lines if ln.lower().startswith(b"sec-websocket-protocol")]
    assert protos == [upstream]
    assert b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==" in up  # the rest of the head as it was
    resp = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n")
    back = rewrite_response(resp, got)
    assert (b"Sec-WebSocket-Protocol: foxglove.websocket.v1" in back) == (answer is not None)
    assert b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=" in back and back.endswith(b"\r\n\r\n")


def test_a_live_port_in_use_is_an_oserror_naming_it():
    import foxglove

    from host.publish.live import LiveServer

    a = LiveServer(foxglove.Context(), port=0)
    try:
        with pytest.raises(OSError, match=f"Cannot start the live view on 127.0.0.1:{a.port}"):
            LiveServer(foxglove.Context(), port=a.port)
    finally:
        a.stop()
