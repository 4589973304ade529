"""The cost of ``--publish zenoh`` and ``--publish ros2`` on the host's receive thread: encoding a
snapshot (`host.publish.zenoh_pub.encode_snapshot`; ros2: a CDR ``capsheet_msgs/LatticeSnapshot``) and one
``Publisher.put`` (ros2: with rmw_zenoh's attachment) in peer mode on loopback, with one subscriber
process-local peer listening (so the put goes to a transport, not to nothing), per lattice size; for
ros2 also an estimate (``sensor_msgs/PointCloud2`` of the joints + ``visualization_msgs/Marker``
TRIANGLE_LIST, encoded and put); for imu a 9-axis snapshot as every link's ``sensor_msgs/Imu`` and
``sensor_msgs/MagneticField`` (``--n`` / 20 snapshots, with orientations: what a 6/9-axis session
publishes per snapshot, in its main thread). Prints JSON: microseconds per message (median of
``--n`` puts) and payload bytes.

    .venv/bin/python benchmarks/bench_publish.py [--n 2000] [--kinds zenoh,ros2,imu]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from host.snapshots.snapshot import LatticeSnapshot  # noqa: F401 -- the type the encoder reads
from host.publish.zenoh_pub import ZenohPublisher, encode_snapshot, zenoh_config
from protocol.lattice import Lattice


class Snap:  # the fields encode_snapshot reads, as a LatticeSnapshot has them
    def __init__(self, n, rng):
        self.counter, self.timestamp, self.wall_time = 1, 1.0, time.time()
        self.readings = rng.normal(size=(n, 3))
        self.valid = np.ones(n, bool)
        self.status = np.zeros(n, np.uint8)


class Est:  # the field Ros2Outputs.estimate reads, as a ShapeEstimate has it
    def __init__(self, joints):
        self.joints, self.joint_std = joints, None


def bench_ros2(sub_session, lat, size, rng, n) -> dict:
    from host.publish.ros2 import Ros2Outputs
    name = f"bench{size}"
    got = [0, 0]
    subs = [sub_session.declare_subscriber(f"0/capsheet/{name}/snapshot/**", lambda s: got.__setitem__(0, got[0] + 1)),
            sub_session.declare_subscriber(f"0/capsheet/{name}/joints/**", lambda s: got.__setitem__(1, got[1] + 1))]
    pub = Ros2Outputs(name, lat, publish=True)
    time.sleep(2.0)  # discovery
    snap = Snap(lat.n_links, rng)
    est = Est(rng.normal(size=(lat.rows, lat.cols, 3)) * 0.01)
    t_snap, t_est, t_enc = [], [], []
    for k in range(n):
        snap.counter = k
        t0 = time.perf_counter()
        pub.snapshot(snap)
        t1 = time.perf_counter()
        t_snap.append(t1 - t0)
    for k in range(max(1, n // 4)):  # estimates: --live-rate per second, not every snapshot
        t0 = time.perf_counter()
        pub.estimate(est, snap)
        t_est.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        pub.encoder.joints(est.joints, None, 0)
        pub.encoder.surface(est.joints, 0)
        t_enc.append(time.perf_counter() - t0)
    time.sleep(1.0)
    enc = pub.encoder
    res = {"links": lat.n_links, "snapshot_bytes": len(enc.snapshot(snap)[0]),
           "snapshot_encode_and_put_us_median": round(1e6 * float(np.median(t_snap)), 1),
           "snapshot_encode_and_put_us_p99": round(1e6 * float(np.percentile(t_snap, 99)), 1),
           "joints_bytes": len(enc.joints(est.joints, None, 0)), "surface_bytes": len(enc.surface(est.joints, 0)),
           "estimate_encode_us_median": round(1e6 * float(np.median(t_enc)), 1),
           "estimate_encode_and_put_us_median": round(1e6 * float(np.median(t_est)), 1),
           "published_snapshots": n, "received_snapshots": got[0],
           "published_estimates": len(t_est), "received_joints": got[1]}
    pub.close()
    for s in subs:
        s.undeclare()
    return res


def bench_imu(sub_session, lat, size, rng, n) -> dict:
    """Every link's Imu and MagneticField of one snapshot (`Ros2Outputs.imu`): encoded for all links
    at once, one put per message."""
    from types import SimpleNamespace

    from host.publish.ros2 import Ros2Outputs
    name = f"benchimu{size}"
    got = [0]
    sub = sub_session.declare_subscriber(f"0/capsheet/{name}/**", lambda s: got.__setitem__(0, got[0] + 1))
    pub = Ros2Outputs(name, lat, publish=True)
    snap = Snap(lat.n_links, rng)
    snap.gyro, snap.mag = rng.normal(size=(lat.n_links, 3)), rng.normal(size=(lat.n_links, 3)) * 5e-5
    snap.sample_time_s = rng.random(lat.n_links) * 1e-3
    from scipy.spatial.transform import Rotation
    motion = SimpleNamespace(frames=Rotation.random(lat.n_links, random_state=1).as_matrix())
    cov = np.tile(np.eye(3) * 1e-6, (lat.n_links, 1, 1))
    pub.imu(snap, motion, cov)  # the links' publishers are declared at the first
    time.sleep(2.0)  # discovery
    got[0] = 0
    t = []
    for k in range(n):
        t0 = time.perf_counter()
        pub.imu(snap, motion, cov)
        t.append(time.perf_counter() - t0)
    time.sleep(1.0)
    per = 2 * lat.n_links
    res = {"links": lat.n_links, "messages_per_snapshot": per,
           "imu_bytes": len(pub.encoder.imu(lat.n_links, np.arange(1), np.zeros(1, np.int64), np.zeros((1, 3)),
                                            np.zeros((1, 3)), None, None, 0.0, 0.0)[0]),
           "snapshot_encode_and_put_ms_median": round(1e3 * float(np.median(t)), 2),
           "per_message_us_median": round(1e6 * float(np.median(t)) / per, 2),
           "published_messages": n * per, "received_messages": got[0]}
    pub.close()
    sub.undeclare()
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--kinds", default="zenoh,ros2,imu")
    args = ap.parse_args()
    kinds = args.kinds.split(",")
    import zenoh
    rng = np.random.default_rng(1)
    sub_session = zenoh.open(zenoh_config(None))
    got = [0]
    out = {}
    for size in ("14x14", "32x32", "64x64"):
        lat = Lattice.parse(size)
        out[size] = {}
        if "ros2" in kinds:
            out[size]["ros2"] = bench_ros2(sub_session, lat, size, rng, args.n)
        if "imu" in kinds:
            out[size]["imu"] = bench_imu(sub_session, lat, size, rng, max(5, args.n // 20))
        if "zenoh" not in kinds:
            continue
        name = f"bench{size}"
        sub = sub_session.declare_subscriber(f"capsheet/{name}/snapshot", lambda s: got.__setitem__(0, got[0] + 1))
        pub = ZenohPublisher(name, None, lat, 0.01)
        time.sleep(2.0)  # discovery
        snap = Snap(lat.n_links, rng)
        enc, put = [], []
        for k in range(args.n):
            snap.counter = k
            t0 = time.perf_counter()
            encode_snapshot(snap, lat.rows, lat.cols)
            t1 = time.perf_counter()
            pub.snapshot(snap)
            t2 = time.perf_counter()
            enc.append(t1 - t0)
            put.append(t2 - t1)
        time.sleep(1.0)
        out[size]["zenoh"] = {"links": lat.n_links, "bytes": len(encode_snapshot(snap, lat.rows, lat.cols)),
                     "encode_us_median": round(1e6 * float(np.median(enc)), 1),
                     "encode_and_put_us_median": round(1e6 * float(np.median(put)), 1),
                     "encode_and_put_us_p99": round(1e6 * float(np.percentile(put, 99)), 1),
                     "published": args.n, "received_by_subscriber": got[0]}
        got[0] = 0
        pub.close()
        sub.undeclare()
    sub_session.close()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
