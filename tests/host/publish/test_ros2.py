"""host/publish/ros2.py against what others publish: REP-2011 type hashes against published values (rmw_zenoh's
docs/design.md) and rosbags' own hasher, CDR against rosbags' decoder and encoder, key expressions
and liveliness tokens against the examples of rmw_zenoh's design.md, the attachment against zenoh's
own deserializer."""

from __future__ import annotations

import struct
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from host.publish import ros2 as R

rosbags = pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore, get_types_from_msg  # noqa: E402

MSGS = Path(__file__).resolve().parents[3] / "msgs" / "capsheet_msgs" / "msg"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # rmw_zenoh design.md


@pytest.fixture(scope="module")
def ts():
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for f in sorted(MSGS.glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"capsheet_msgs/msg/{f.stem}"))
    store.register(types)
    return store


def test_type_hashes_are_the_published_ones():
    # rmw_zenoh docs/design.md's chatter example (std_msgs/msg/String); a PointCloud2 token published by
    # an rmw_zenoh interoperability example (sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198...)
    assert R.rihs01("std_msgs/msg/String") == STRING_HASH
    assert R.rihs01("sensor_msgs/msg/PointCloud2") == \
        "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"


def test_every_type_hash_is_rosbags(ts):
    names = set(R.TOPICS.values()) | {"capsheet_msgs/msg/Contact", "geometry_msgs/msg/Pose", "std_msgs/msg/Header",
                                      R.IMU_TYPE, R.MAG_TYPE}
    for n in sorted(names):
        assert R.rihs01(n) == ts.hash_rihs01(n), n


def test_an_empty_message_and_a_bounded_field_hash_as_rosbags(ts):
    reg = R.TypeRegistry()
    reg.add("test_msgs/msg/Empty", "# nothing\n")
    reg.add("test_msgs/msg/Bounded", "string<=8 name\nint32[4] fixed\nfloat64[<=3] up_to\nEmpty e\nint8 K=3\n")
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg("", "test_msgs/msg/Empty"))
    store.register(get_types_from_msg("string<=8 name\nint32[4] fixed\nfloat64[<=3] up_to\nEmpty e\nint8 K=3\n",
                                      "test_msgs/msg/Bounded"))
    assert reg.rihs01("test_msgs/msg/Empty") == store.hash_rihs01("test_msgs/msg/Empty")
    assert reg.rihs01("test_msgs/msg/Bounded") == store.hash_rihs01("test_msgs/msg/Bounded")


def _snap(rng, n):
    s = SimpleNamespace(counter=70000, timestamp=123.25, wall_time=1.7e9 + 0.5, readings=rng.normal(size=(n, 3)) * 9.8,
                        valid=rng.random(n) > 0.2, status=rng.integers(0, 256, n).astype(np.uint8))
    s.readings[~s.valid] = np.nan
    return s


@pytest.mark.parametrize("rows, cols", [(2, 2), (3, 5), (14, 14)])
def test_cdr_is_what_rosbags_reads_and_writes(ts, rows, cols):
    rng = np.random.default_rng(rows * 100 + cols)
    n = rows * (cols - 1) + cols * (rows - 1)
    enc = R.Ros2Encoder("left", rows, cols)
    snap = _snap(rng, n)
    joints = rng.normal(size=(rows, cols, 3)) * 0.01
    std = rng.random((rows, cols)) * 1e-3
    contact = SimpleNamespace(id=-1, index=np.array([1.5, 0.25]), position=np.array([0.01, 0.02, -0.003]),
                              force_n=0.8, depth_m=0.002, area_m2=3e-5, axes_m=np.array([0.004, 0.003]))
    payload, stamp = enc.snapshot(snap)
    cases = [(payload, "capsheet_msgs/msg/LatticeSnapshot"),
             (enc.joints(joints, std, stamp), "sensor_msgs/msg/PointCloud2"),
             (enc.joints(joints, None, stamp), "sensor_msgs/msg/PointCloud2"),
             (enc.surface(joints, stamp), "visualization_msgs/msg/Marker"),
             (enc.contacts(9, stamp, [contact, contact], 1.6), "capsheet_msgs/msg/Contacts"),
             (enc.contacts(10, stamp, [], 0.0), "capsheet_msgs/msg/Contacts"),
             (enc.diagnostics({"links": n, "missing_links": [{"link": 3}], "complete_snapshots_pct": 50.0,
                               "snapshots": 4}, stamp), "diagnostic_msgs/msg/DiagnosticArray")]
    for data, typ in cases:
        assert data[:4] == b"\x00\x01\x00\x00"  # CDR little-endian
        msg = ts.deserialize_cdr(data, typ)
        assert bytes(ts.serialize_cdr(msg, typ)) == data, typ
    m = ts.deserialize_cdr(cases[0][0], cases[0][1])
    assert (m.counter, m.host_time, m.rows, m.cols) == (70000, 123.25, rows, cols)
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == \
        (1_700_000_000, 500_000_000, "capsheet_left")
    np.testing.assert_array_equal(np.asarray(m.valid, bool), snap.valid)
    np.testing.assert_array_equal(m.status, snap.status)
    np.testing.assert_allclose(m.specific_force.reshape(-1, 3), snap.readings.astype(np.float32), equal_nan=True)
    pc = ts.deserialize_cdr(cases[1][0], cases[1][1])
    pts = np.frombuffer(pc.data.tobytes(), "<f4").reshape(rows, cols, 4)
    np.testing.assert_array_equal(pts[..., :3], joints.astype(np.float32))
    np.testing.assert_array_equal(pts[..., 3], std.astype(np.float32))
    assert np.isnan(np.frombuffer(ts.deserialize_cdr(cases[2][0], cases[2][1]).data.tobytes(), "<f4")[3::4]).all()
    mk = ts.deserialize_cdr(cases[3][0], cases[3][1])
    assert mk.type == mk.TRIANGLE_LIST and len(mk.points) == 6 * (rows - 1) * (cols - 1)
    assert (mk.points[0].x, mk.points[0].y, mk.points[0].z) == tuple(joints[0, 0])  # cell (0, 0): (0,0), (1,0), (0,1)
    assert (mk.points[1].x, mk.points[2].x) == (joints[1, 0, 0], joints[0, 1, 0])
    ct = ts.deserialize_cdr(cases[4][0], cases[4][1])
    c = ct.contacts[1]
    assert (ct.frame, ct.total_force_n, c.id, c.row, c.col, c.position.z, c.radius_m) == \
        (9, 1.6, -1, 1.5, 0.25, -0.003, 0.004)
    dg = ts.deserialize_cdr(cases[6][0], cases[6][1]).status[0]
    assert dg.level == dg.WARN and {kv.key for kv in dg.values} == {"links", "missing_links", "complete_snapshots_pct",
                                                                    "snapshots"}


def test_key_expressions_and_tokens_are_rmw_zenohs_examples():
    # rmw_zenoh docs/design.md, "Topic and Service name mapping" and "Graph Cache"
    assert R.topic_keyexpr(0, "/chatter", "std_msgs/msg/String") == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert R.topic_keyexpr(0, "/robot1/chatter", "std_msgs/msg/String") == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert R.liveliness_keyexpr(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 0, "NN", "/", "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    talker = dict(R.DEFAULT_QOS, depth=7)  # demo_nodes_cpp's talker: reliable, volatile, keep last 7
    assert R.liveliness_keyexpr(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "MP", "/", "talker", "/chatter",
                                "std_msgs/msg/String", talker) == \
        ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
         f"{STRING_HASH}/::,7:,:,:,,")
    assert R.qos_keyexpr(R.DEFAULT_QOS) == "::,10:,:,:,,"  # the listener's, in the same examples
    assert R.qos_keyexpr(R.SENSOR_QOS) == "2::,5:,:,:,,"


def test_the_attachment_is_what_zenoh_ext_deserializes():
    import zenoh
    from zenoh.ext import Int64, z_deserialize

    gid = R.publisher_gid("@ros2_lv/0/abc/0/1/MP/%/%capsheet/s/%capsheet%s%joints/x/y/z")
    now = time.time_ns()
    att = R.attachment(41, now, gid)
    # design.md: int64 sequence, int64 timestamp (little-endian), 1 byte GID length (16), the GID:
    # zenoh-ext's serialization of (int64, int64, 16 bytes), what rmw_zenoh's AttachmentData writes
    assert len(att) == 33 and struct.unpack_from("<qqB", att) == (41, now, 16)
    assert z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(att)) == (41, now, gid)
    import xxhash  # XXH3-128's canonical form is big-endian: rmw_zenoh stores low then high, each little-endian
    assert gid == xxhash.xxh3_128_digest(b"@ros2_lv/0/abc/0/1/MP/%/%capsheet/s/%capsheet%s%joints/x/y/z")[::-1]


@pytest.mark.parametrize("value, expect", [(None, 0), ("", 0), ("7", 7), ("232", 232), ("233", None),
                                           ("-1", None), ("x", None)])
def test_ros_domain_id(value, expect):
    env = {} if value is None else {"ROS_DOMAIN_ID": value}
    if expect is None:
        with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
            R.domain_id(env)
    else:
        assert R.domain_id(env) == expect


def test_the_ros2msg_schema_is_what_rosbags_parses(ts):
    reg = R.registry()
    for typ in sorted(set(R.TOPICS.values()) | {R.IMU_TYPE, R.MAG_TYPE}):
        text = reg.msgdef(typ)
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(text, typ))  # rosbags reads the concatenated definition
        assert store.hash_rihs01(typ) == R.rihs01(typ), typ


def test_a_failing_recording_is_counted_not_raised():
    """A sink that fails (here a full disk: /dev/full) never raises into the caller (the host's
    receive thread) nor at close: counted, with its reason; the recording stops at the first failure."""
    from protocol.lattice import Lattice
    out = R.Ros2Outputs("s", Lattice(14, 14), record="/dev/full")
    rng = np.random.default_rng(3)
    snap = _snap(rng, 364)
    for _ in range(400):  # 5 kB each: past the MCAP writer's 1 MB chunk, which it then writes
        out.snapshot(snap)
    assert out.counts["snapshot"] == 400 and out.failed["record"] >= 1 and out.failed["publish"] == 0
    assert "No space left" in out.last_error["record"] or "28" in out.last_error["record"]
    out.close()


def test_link_names_sort_in_the_lattices_order():
    assert R.imu_topics(12) == [f"link_{k:03d}" for k in range(12)]
    names = R.imu_topics(8064)  # a 64x64 sheet: 4 digits, every name as wide
    assert names[0] == "link_0000" and names[-1] == "link_8063" and names == sorted(names)


def _imu_snap(rng, n):
    s = _snap(rng, n)
    s.valid[:] = True
    s.readings = rng.normal(size=(n, 3))
    s.gyro = rng.normal(size=(n, 3))
    s.mag = rng.normal(size=(n, 3)) * 5e-5
    s.sample_time_s = rng.random(n) * 4e-3
    s.gyro[2] = np.nan  # link 2 sent no IMU record
    s.valid[5] = False  # link 5 did not answer
    s.mag[7] = np.nan  # link 7's magnetometer sample is missing
    s.sample_time_s[9] = np.nan  # link 9's sample time unknown: the SYNC's
    return s


@pytest.mark.parametrize("fused", [True, False])
def test_the_links_imu_messages_are_what_rosbags_reads(ts, tmp_path, fused):
    """Per link that sent an IMU record, one ``sensor_msgs/msg/Imu`` on ``link_<k>/imu/data`` and
    one ``MagneticField`` on ``link_<k>/imu/mag``, stamped at the link's sample time, in its frame,
    with the covariances given; read back from the MCAP by rosbags."""
    from rosbags.rosbag2 import Reader
    from scipy.spatial.transform import Rotation

    from protocol.lattice import Lattice
    rng = np.random.default_rng(7 + fused)
    lat = Lattice(3, 3)
    n = lat.n_links
    snaps = [_imu_snap(rng, n) for _ in range(3)]
    quats = Rotation.random(n, random_state=5).as_quat()  # x, y, z, w
    motion = SimpleNamespace(frames=Rotation.from_quat(quats).as_matrix()) if fused else None
    A = rng.normal(size=(n, 3, 3))
    ocov = A @ A.transpose(0, 2, 1) * 1e-6  # symmetric, positive
    noise = SimpleNamespace(accel_noise_mps2=0.1, gyro_noise_rps=0.002, mag_noise_t=4e-7)
    out = R.Ros2Outputs("arm", lat, record=tmp_path / "imu.mcap")
    for s in snaps:
        out.imu(s, motion, ocov if fused else None, noise)
    out.close()
    sent = [k for k in range(n) if k not in (2, 5)]
    assert out.counts["imu"] == 3 * len(sent) and out.counts["mag"] == 3 * (len(sent) - 1)
    with Reader(tmp_path / "imu.mcap") as r:
        conns = {c.topic: c for c in r.connections}
        got = {t: [ts.deserialize_cdr(raw, c.msgtype) for c, _, raw in r.messages([c])] for t, c in conns.items()}
    assert set(conns) == {f"/capsheet/arm/link_{k:03d}/imu/data" for k in sent} | \
        {f"/capsheet/arm/link_{k:03d}/imu/mag" for k in sent if k != 7}
    for k in sent:
        imu = got[f"/capsheet/arm/link_{k:03d}/imu/data"]
        assert conns[f"/capsheet/arm/link_{k:03d}/imu/data"].msgtype == "sensor_msgs/msg/Imu" and len(imu) == 3
        for s, m in zip(snaps, imu):
            dt = 0.0 if k == 9 else s.sample_time_s[k]
            assert m.header.frame_id == f"capsheet_arm_link_{k:03d}"
            assert abs(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec - (s.wall_time + dt)) < 1e-6
            v = lambda x: [x.x, x.y, x.z]  # noqa: E731
            assert v(m.angular_velocity) == s.gyro[k].tolist() and v(m.linear_acceleration) == s.readings[k].tolist()
            np.testing.assert_allclose(m.angular_velocity_covariance, np.diag([0.002 ** 2] * 3).ravel())
            np.testing.assert_allclose(m.linear_acceleration_covariance, np.diag([0.01] * 3).ravel())
            q = [m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w]
            if fused:  # the same rotation (a quaternion or its negative)
                assert min(np.abs(np.subtract(q, quats[k])).max(), np.abs(np.add(q, quats[k])).max()) < 1e-12
                np.testing.assert_allclose(m.orientation_covariance, ocov[k].ravel())
            else:  # REP 145 / Imu.msg: no orientation estimate
                assert m.orientation_covariance[0] == -1.0
        if k == 7:
            continue
        for s, m in zip(snaps, got[f"/capsheet/arm/link_{k:03d}/imu/mag"]):
            assert m.header.frame_id == f"capsheet_arm_link_{k:03d}"
            assert [m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z] == s.mag[k].tolist()
            np.testing.assert_allclose(m.magnetic_field_covariance, np.diag([1.6e-13] * 3).ravel())
