"""A ROS 2 subscriber without ROS, in its own process, for tests/host/cli/test_publish_ros2.py. It
knows the zenoh API, rmw_zenoh's documented layout (its docs/design.md: key expressions, the
attachment, liveliness tokens) and decodes with rosbags' type store (capsheet_msgs registered from
the repository's .msg files) — not host.ros2. Prints one JSON line: what it received and decoded.

    python ros2_subscriber.py DOMAIN SHEET SECONDS MIN_JOINTS [LISTEN]

LISTEN (a locator, e.g. tcp/127.0.0.1:7450): listen there with multicast scouting off (the host
connects to it: ``--publish ros2:LISTEN``); without it, a peer on loopback meeting the others at
tcp/127.0.0.1:7447 as capsheet's default sessions do.
"""

import json
import os
import re
import struct
import sys
import time
from pathlib import Path

import xxhash
import zenoh
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

domain, sheet, seconds, min_joints = int(sys.argv[1]), sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
ts = get_typestore(Stores.ROS2_JAZZY)
msgs = Path(__file__).resolve().parents[3] / "msgs" / "capsheet_msgs" / "msg"
types = {}
for f in sorted(msgs.glob("*.msg")):
    types.update(get_types_from_msg(f.read_text(), f"capsheet_msgs/msg/{f.stem}"))
ts.register(types)

listen = sys.argv[5] if len(sys.argv) > 5 else None
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
if listen:
    conf.insert_json5("listen/endpoints", json.dumps([listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
else:  # docs/distribution.md: without multicast, the machine's sessions meet at tcp/127.0.0.1:7447
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0", "tcp/127.0.0.1:7447#exit_on_failure=false"]')
    conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    # ZENOH_CONFIG_OVERRIDE (rmw_zenoh's key=value;... pairs, docs/distribution.md), applied last as capsheet
    # applies it: where the test run's sessions meet (tests/zenoh_meeting.py)
    for item in filter(None, os.environ.get("ZENOH_CONFIG_OVERRIDE", "").split(";")):
        conf.insert_json5(*(s.strip() for s in item.split("=", 1)))
session = zenoh.open(conf)
out = {"samples": {}, "keys": {}, "bad": [], "tokens": [], "tokens_gone": [], "attachments": {},
       "diagnostics": []}
# rmw_zenoh docs/design.md: <domain>/<fully qualified name>/<pkg>::msg::dds_::<Type>_/RIHS01_<64 hex>
DATA_KEY = re.compile(r"^(\d+)/(.+)/([A-Za-z0-9_]+)::msg::dds_::([A-Za-z0-9_]+)_/RIHS01_([0-9a-f]{64})$")
clouds, markers = {}, []  # joints by header stamp; (stamp, vertices) of every surface
ATT = struct.Struct("<qqB")  # int64 sequence, int64 source timestamp (ns), GID length; then the GID


def on_sample(sample):
    key, data = str(sample.key_expr), bytes(sample.payload.to_bytes())
    try:
        m = DATA_KEY.match(key)
        assert m, f"not an rmw_zenoh topic key: {key}"
        assert int(m[1]) == domain
        typ = f"{m[3]}/msg/{m[4]}"
        assert "RIHS01_" + m[5] == ts.hash_rihs01(typ), f"{key}: hash is not {typ}'s"  # rosbags' REP-2011 hash
        topic = "/" + m[2]
        assert data[:4] == b"\x00\x01\x00\x00", f"{key}: not CDR little-endian ({data[:4].hex()})"
        msg = ts.deserialize_cdr(data, typ)
        assert bytes(ts.serialize_cdr(msg, typ)) == data, f"{key}: rosbags writes other bytes for what it read"
        att = bytes(sample.attachment.to_bytes()) if sample.attachment is not None else b""
        seq, stamp, n = ATT.unpack_from(att)
        assert n == 16 and len(att) == ATT.size + 16, f"{key}: attachment of {len(att)} bytes, GID length {n}"
        a = out["attachments"].setdefault(topic, {"seq": [], "stamps_ns": [], "gids": []})
        a["seq"].append(seq)
        a["stamps_ns"].append(stamp)
        gid = att[ATT.size:].hex()
        if gid not in a["gids"]:
            a["gids"].append(gid)
        if topic == "/diagnostics":
            st = msg.status[0]
            if st.name.endswith(sheet):  # other sheets may share the domain's /diagnostics
                out["diagnostics"].append({"name": st.name, "level": int(st.level),
                                           "values": {kv.key: kv.value for kv in st.values}})
            return
        out["keys"][topic] = key
        s = out["samples"].setdefault(topic, [])
        if typ == "capsheet_msgs/msg/LatticeSnapshot":
            import numpy as np
            g = np.asarray(msg.specific_force).reshape(-1, 3)
            v = np.asarray(msg.valid, bool)
            s.append({"counter": int(msg.counter), "rows": msg.rows, "cols": msg.cols, "n": len(v),
                      "valid": int(v.sum()), "frame_id": msg.header.frame_id,
                      "norm": float(np.median(np.linalg.norm(g[v], axis=1))) if v.any() else None})
        elif typ == "sensor_msgs/msg/PointCloud2":
            import numpy as np
            names = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
            pts = np.frombuffer(msg.data.tobytes(), "<f4").reshape(msg.height, msg.width, msg.point_step // 4)
            link = np.linalg.norm(np.diff(pts[..., :3], axis=1), axis=2)
            std = pts[..., 3]
            clouds[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = pts[..., :3].reshape(-1, 3)
            s.append({"height": msg.height, "width": msg.width, "fields": names, "point_step": msg.point_step,
                      "row_step": msg.row_step, "link_m": float(np.median(link)), "is_dense": bool(msg.is_dense),
                      "std": None if np.isnan(std).all() else float(np.nanmax(std)),
                      "stamp": msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec})
        elif typ == "visualization_msgs/msg/Marker":
            import numpy as np
            p = np.array([[q.x, q.y, q.z] for q in msg.points])
            tri = p.reshape(-1, 3, 3)
            edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
            markers.append(((msg.header.stamp.sec, msg.header.stamp.nanosec), p))
            s.append({"type": int(msg.type), "action": int(msg.action), "points": len(p),
                      "edge_m_min": float(edges.min()), "edge_m_max": float(edges.max()),
                      "frame_id": msg.header.frame_id})
        elif typ == "sensor_msgs/msg/Imu":  # REP 145: orientation sensor -> fixed frame, +g up at rest
            import numpy as np
            q = np.array([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w])
            f = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
            w = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
            s.append({"frame_id": msg.header.frame_id, "stamp": msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec,
                      "q": q.tolist(), "f": f.tolist(), "w": w.tolist(),
                      "ocov": msg.orientation_covariance.tolist(), "wcov": msg.angular_velocity_covariance.tolist(),
                      "fcov": msg.linear_acceleration_covariance.tolist()})
        elif typ == "sensor_msgs/msg/MagneticField":
            m = msg.magnetic_field
            s.append({"frame_id": msg.header.frame_id, "stamp": msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec,
                      "m": [m.x, m.y, m.z], "cov": msg.magnetic_field_covariance.tolist()})
        else:
            s.append({"type": typ})
    except Exception as exc:  # noqa: BLE001 - reported, the test fails on it
        out["bad"].append(f"{key}: {exc!r}")


def on_info(sample):
    key, data = str(sample.key_expr), bytes(sample.payload.to_bytes())
    try:
        m = DATA_KEY.match(key)
        assert m and f"{m[3]}/msg/{m[4]}" == "std_msgs/msg/String", key
        assert "RIHS01_" + m[5] == ts.hash_rihs01("std_msgs/msg/String")
        out["late_info"] = ts.deserialize_cdr(data, "std_msgs/msg/String").data
    except Exception as exc:  # noqa: BLE001 - reported, the test fails on it
        out["bad"].append(f"{key}: {exc!r}")


def on_token(sample):
    key = str(sample.key_expr)
    if sample.kind == zenoh.SampleKind.DELETE:
        out["tokens_gone"].append(key)
    elif key not in out["tokens"]:
        out["tokens"].append(key)
        if "/MP/" in key:  # rmw_zenoh's GID: XXH3-128 of the liveliness key, low then high 64 bits
            gid = xxhash.xxh3_128_intdigest(key.encode()).to_bytes(16, "little")
            out.setdefault("gid_of_token", {})[key] = gid.hex()


subs = [session.declare_subscriber(f"{domain}/capsheet/{sheet}/**", on_sample),
        session.declare_subscriber(f"{domain}/diagnostics/**", on_sample),
        session.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", on_token, history=True)]
print("ready", flush=True)
end = time.monotonic() + seconds
asked = False
while time.monotonic() < end:
    if not asked and len(out["samples"].get(f"/capsheet/{sheet}/joints", [])) >= min_joints:
        asked = True  # a graph query, as a ROS 2 context starting late makes it (liveliness get)
        out["tokens_queried"] = [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{domain}/**",
                                                                                     timeout=5.0) if r.ok]
        # the latched info topic (transient local), asked late as rmw_zenoh's transient-local
        # subscription does: an advanced subscriber with history, detecting late publishers
        import zenoh.ext as zx
        subs.append(zx.declare_advanced_subscriber(
            session, f"{domain}/capsheet/{sheet}/info/**", on_info,
            history=zx.HistoryConfig(detect_late_publishers=True)))
    if out["tokens_gone"] and asked:  # the host has gone (its tokens withdrawn): wait a moment for stragglers
        end = min(end, time.monotonic() + 1.0)
    time.sleep(0.05)
for s in subs:
    s.undeclare()
session.close()
# each surface's vertices are the joints of the cloud with the same stamp, in triangles that tile
# the lattice's cells, two per cell: [joint indices (row-major) of each triangle, sorted]
out["surface_triangles"] = []
for stamp, p in markers:
    if stamp in clouds:
        import numpy as np
        j = clouds[stamp]
        d = np.linalg.norm(p[:, None, :] - j[None, :, :], axis=2)
        idx = d.argmin(axis=1)
        out["surface_triangles"].append({"max_off_m": float(d.min(axis=1).max()),
                                         "triangles": sorted(sorted(int(i) for i in t) for t in idx.reshape(-1, 3))})
print(json.dumps(out), flush=True)
