"""The lattice's `foxglove.SceneUpdate`, encoded with numpy (host/publish/live.py, `_LineListScene`): the
bytes `SceneChannels.log_lattice` logs decode (google.protobuf, with the schema foxglove-sdk ships)
to the message the SDK's own objects encode to — the object-based code it replaced, kept here as the
reference — and read back from a real MCAP file by the ``mcap`` package's reader, on a channel that
is the one the SDK's typed `SceneUpdateChannel` made.

``python tests/host/publish/test_scene_encoding.py`` times both on a 64x64 sheet (median of 20 calls)."""

from __future__ import annotations

import numpy as np
import pytest

foxglove = pytest.importorskip("foxglove")

from host.publish.live import SceneChannels  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402

T_NS = 1_700_000_123_456_789_012


def _message_class(name: str):
    """The google.protobuf class of ``name`` from the FileDescriptorSet of the SDK's SceneUpdate schema."""
    from foxglove.messages import SceneUpdate
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(SceneUpdate.get_schema().data).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


SceneUpdatePb = _message_class("foxglove.SceneUpdate")


def decode(data: bytes):
    return SceneUpdatePb.FromString(data)


def assert_same_message(data: bytes, reference: bytes) -> None:
    """Equal once decoded, and equal re-encoded (deterministic: the sign of a zero, a NaN's bits)."""
    got, want = decode(data), decode(reference)
    assert got == want
    assert got.SerializeToString(deterministic=True) == want.SerializeToString(deterministic=True)


# -- the reference: host/publish/live.py's log_lattice before, one Point3 and one Color object per vertex -----
def reference_scene_update(sc: SceneChannels, joints, valid, t_ns: int, *, error=None, displacement=None):
    from foxglove.messages import (Color, LinePrimitive, LinePrimitiveLineType, Point3, SceneEntity,
                                   SceneUpdate, Timestamp)

    P = np.asarray(joints, dtype=float).reshape(-1, 3)
    ts = Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000))
    cols = sc.link_colours(np.asarray(valid, dtype=bool), error, displacement)
    pts = P[sc._ends.ravel()]
    line = LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True,
                         points=[Point3(x=x, y=y, z=z) for x, y, z in pts.tolist()],
                         colors=[Color(r=r, g=g, b=b_, a=al) for r, g, b_, al in cols.tolist()])
    return SceneUpdate(entities=[SceneEntity(timestamp=ts, frame_id=sc.frame_id, id="lattice", lines=[line])])


def reference_point_cloud(sc: SceneChannels, joints, t_ns: int):
    from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud, Timestamp

    P = np.asarray(joints, dtype=float).reshape(-1, 3)
    f32 = PackedElementFieldNumericType.Float32
    return PointCloud(timestamp=Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000)),
                      frame_id=sc.frame_id, point_stride=12,
                      fields=[PackedElementField(name=n, offset=4 * k, type=f32) for k, n in enumerate("xyz")],
                      data=P.astype("<f4").tobytes())


def object_log_lattice(sc: SceneChannels, joints, valid, t_ns: int, *, error=None, displacement=None) -> None:
    """The old log_lattice (SDK objects, the typed channel encodes): for the timing."""
    if not (sc.scene.has_sinks() or sc.cloud.has_sinks()):
        return
    sc.scene.log(reference_scene_update(sc, joints, valid, t_ns, error=error, displacement=displacement),
                 log_time=t_ns)
    sc.cloud.log(reference_point_cloud(sc, joints, t_ns), log_time=t_ns)


class Capture:
    """Stands for a channel with a sink: keeps what is logged."""

    def __init__(self):
        self.logged = []

    def has_sinks(self) -> bool:
        return True

    def log(self, msg, *, log_time=None, sink_id=None):
        self.logged.append((msg, log_time))


def sample(lattice: Lattice, seed: int):
    """Joints with exact 0.0 and -0.0 coordinates, a valid mask with missing links (always link 0),
    per-joint errors and displacements (one of them 0)."""
    rng = np.random.Generator(np.random.MT19937(seed))
    J = rng.normal(scale=0.05, size=(lattice.rows, lattice.cols, 3))
    J[0, 0] = 0.0  # a joint at the origin: every coordinate omitted by proto3
    J[..., 2][rng.random(J.shape[:2]) < 0.3] = 0.0  # flat parts
    J[-1, -1, 1] = -0.0
    J[..., 0][rng.random(J.shape[:2]) < 0.05] = -0.0
    valid = rng.random(lattice.n_links) > 0.1
    valid[0] = False
    error = rng.random((lattice.rows, lattice.cols)) * 3.0
    error[0, 0] = 0.0
    displacement = rng.normal(scale=0.002, size=(lattice.rows, lattice.cols))
    displacement[0, 1] = 0.0
    return J, valid, error, displacement


# -- the schema the encoder was written from --------------------------------------------------------
def test_the_encoders_field_numbers_are_the_sdks_schemas():
    from google.protobuf.descriptor import FieldDescriptor as F

    from host.publish.live import _FIELDS, _LINE_LIST

    for key, number in _FIELDS.items():
        message, field = key.split(".")
        full = "google.protobuf.Timestamp" if message == "Timestamp" else f"foxglove.{message}"
        assert _message_class(full).DESCRIPTOR.fields_by_name[field].number == number, key
    assert _message_class("foxglove.LinePrimitive").Type.Value("LINE_LIST") == _LINE_LIST
    # the wire types the encoder writes them with
    types = {"double": F.TYPE_DOUBLE, "message": F.TYPE_MESSAGE, "string": F.TYPE_STRING, "enum": F.TYPE_ENUM,
             "bool": F.TYPE_BOOL, "int64": F.TYPE_INT64, "int32": F.TYPE_INT32}
    want = {"Point3": {f: "double" for f in "xyz"}, "Color": {f: "double" for f in "rgba"},
            "LinePrimitive": {"type": "enum", "thickness": "double", "scale_invariant": "bool",
                              "points": "message", "colors": "message"},
            "SceneEntity": {"timestamp": "message", "frame_id": "string", "id": "string", "lines": "message"},
            "SceneUpdate": {"entities": "message"}, "Timestamp": {"seconds": "int64", "nanos": "int32"}}
    for message, fields in want.items():
        full = "google.protobuf.Timestamp" if message == "Timestamp" else f"foxglove.{message}"
        for field, kind in fields.items():
            d = _message_class(full).DESCRIPTOR.fields_by_name[field]
            assert d.type == types[kind] and d.is_repeated == (field in ("points", "colors", "lines", "entities"))


# -- the bytes log_lattice logs -----------------------------------------------------------------------
@pytest.mark.parametrize("colour_by", ["links", "error", "displacement"])
@pytest.mark.parametrize("shape, seed", [((3, 4), 1), ((14, 14), 2), ((64, 64), 3)])
def test_log_lattice_bytes_decode_to_the_message_of_the_sdks_objects(shape, seed, colour_by):
    lat = Lattice(*shape)
    J, valid, error, displacement = sample(lat, seed)
    sc = SceneChannels(foxglove.Context(), lat, colour_by=colour_by, frame_id="sheet")
    sc.scene, sc.cloud = Capture(), Capture()
    for t_ns in (T_NS, T_NS + 1, 5_000_000_000, 999, 0):  # nanos or seconds 0: omitted by proto3
        sc.log_lattice(J, valid, t_ns, error=error, displacement=displacement)
        data, log_time = sc.scene.logged[-1]
        assert isinstance(data, bytes) and log_time == t_ns
        ref = reference_scene_update(sc, J, valid, t_ns, error=error, displacement=displacement).encode()
        assert_same_message(data, ref)
        msg = decode(data)
        assert [e.id for e in msg.entities] == ["lattice"] and len(msg.entities[0].lines) == 1
        assert len(msg.entities[0].lines[0].points) == 2 * lat.n_links  # a missing link drawn too
        cloud, cloud_time = sc.cloud.logged[-1]  # the point cloud unchanged
        assert cloud.encode() == reference_point_cloud(sc, J, t_ns).encode() and cloud_time == t_ns
    assert len(sc.scene.logged) == len(sc.cloud.logged) == 5


def test_zeros_negative_zeros_and_other_frames():
    lat = Lattice(2, 3)
    sc = SceneChannels(foxglove.Context(), lat, frame_id="", prefix="/a")
    sc.scene = Capture()
    J = np.zeros((2, 3, 3))
    J[1] = -0.0
    valid = np.zeros(lat.n_links, bool)
    sc.log_lattice(J, valid, T_NS)
    data = sc.scene.logged[-1][0]
    assert_same_message(data, reference_scene_update(sc, J, valid, T_NS).encode())
    line = decode(data).entities[0].lines[0]
    assert all(np.copysign(1.0, v) == 1.0 for p in line.points for v in (p.x, p.y, p.z))  # -0.0 -> +0.0, as the SDK
    sc2 = SceneChannels(foxglove.Context(), lat, frame_id="sheet_b", prefix="/b")
    sc2.scene = Capture()
    J2 = np.random.default_rng(0).normal(size=(2, 3, 3)) * 1e30  # large values, their bits kept
    t_ns = (2**32 - 1) * 1_000_000_000 + 999_999_999  # the SDK's last Timestamp (sec: u32): 5-byte varints
    sc2.log_lattice(J2, ~valid, t_ns)
    assert_same_message(sc2.scene.logged[-1][0], reference_scene_update(sc2, J2, ~valid, t_ns).encode())
    assert decode(sc2.scene.logged[-1][0]).entities[0].timestamp.seconds == 2**32 - 1
    for t_ns in (-1, 2**32 * 1_000_000_000):  # what the SDK's Timestamp refuses: refused, nothing logged
        with pytest.raises(OverflowError):
            sc2.log_lattice(J2, valid, t_ns)
    assert len(sc2.scene.logged) == 1


def test_nothing_is_encoded_for_a_channel_without_sinks(tmp_path):
    lat = Lattice(3, 3)
    ctx = foxglove.Context()
    sc = SceneChannels(ctx, lat)
    calls = []
    encode = sc._lines.encode
    sc._lines.encode = lambda *a, **k: calls.append(1) or encode(*a, **k)
    J, valid = np.zeros((3, 3, 3)), np.ones(lat.n_links, bool)
    assert not sc.scene.has_sinks()
    sc.log_lattice(J, valid, T_NS)
    assert calls == []
    with foxglove.open_mcap(str(tmp_path / "a.mcap"), context=ctx):
        assert sc.scene.has_sinks()
        sc.log_lattice(J, valid, T_NS)
    assert calls == [1]


def test_contacts_still_go_out_on_the_same_channel():
    sc = SceneChannels(foxglove.Context(), Lattice(3, 3))
    sc.scene = Capture()
    sc.log_contacts([{"id": 4, "position": [0.01, 0.0, -0.0], "force_n": 2.5, "radius_m": 0.004},
                     {"id": 5, "force_n": 1.0}], T_NS)
    data, log_time = sc.scene.logged[-1]
    msg = decode(data)
    assert isinstance(data, bytes) and log_time == T_NS
    assert [e.id for e in msg.entities] == ["contacts"] and msg.entities[0].frame_id == "sheet"
    assert [t.text for t in msg.entities[0].texts] == ["#4 2.50 N"] and len(msg.entities[0].spheres) == 1


# -- a real MCAP file, read by the mcap package -------------------------------------------------------
def _write(path, lat, J, valid, error, metadata, typed: bool):
    """An MCAP file of one lattice and one contact, through a foxglove context sink; ``typed``: on the
    SDK's SceneUpdateChannel with its objects (what log_lattice did before), else SceneChannels'."""
    from foxglove.channels import SceneUpdateChannel

    ctx = foxglove.Context()
    with foxglove.open_mcap(str(path), allow_overwrite=True, context=ctx):
        if typed:
            sc = SceneChannels(foxglove.Context(), lat, colour_by="error", metadata=metadata)  # for its colours
            ch = SceneUpdateChannel("/sheet/scene", context=ctx, metadata=metadata)
            ch.log(reference_scene_update(sc, J, valid, T_NS, error=error), log_time=T_NS)
        else:
            sc = SceneChannels(ctx, lat, colour_by="error", metadata=metadata)
            sc.log_lattice(J, valid, T_NS, error=error)
            sc.log_contacts([{"id": 1, "position": [0.0, 0.01, 0.0], "force_n": 1.5}], T_NS + 1)
    return sc


def _read(path, topic="/sheet/scene"):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(s, c, m) for s, c, m in make_reader(f).iter_messages(topics=[topic])]


def test_an_mcap_file_holds_the_sdks_scene_channel_and_message(tmp_path):
    from foxglove.messages import SceneUpdate

    lat = Lattice(14, 14)
    J, valid, error, _ = sample(lat, 7)
    meta = {"capsheet.sink": "file"}
    sc = _write(tmp_path / "numpy.mcap", lat, J, valid, error, meta, typed=False)
    _write(tmp_path / "objects.mcap", lat, J, valid, error, meta, typed=True)
    got, want = _read(tmp_path / "numpy.mcap"), _read(tmp_path / "objects.mcap")
    assert len(got) == 2 and len(want) == 1
    (schema, channel, message), (schema0, channel0, message0) = got[0], want[0]
    assert (schema.name, schema.encoding, channel.message_encoding) == ("foxglove.SceneUpdate", "protobuf", "protobuf")
    assert schema.data == SceneUpdate.get_schema().data == schema0.data
    assert (schema.name, schema.encoding) == (schema0.name, schema0.encoding)
    assert (channel.topic, channel.message_encoding, channel.metadata) == (
        channel0.topic, channel0.message_encoding, channel0.metadata)
    assert channel.metadata["capsheet.sink"] == "file"
    assert message.log_time == message0.log_time == T_NS
    assert_same_message(message.data, message0.data)
    assert_same_message(message.data, reference_scene_update(sc, J, valid, T_NS, error=error).encode())
    assert decode(got[1][2].data).entities[0].id == "contacts"
    joints = _read(tmp_path / "numpy.mcap", "/sheet/joints")
    assert len(joints) == 1 and joints[0][0].name == "foxglove.PointCloud"
    assert joints[0][2].data == reference_point_cloud(sc, J, T_NS).encode()
