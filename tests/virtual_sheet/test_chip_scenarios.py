"""Every chip implementation against tests/vectors/chip.json (protocol/scenarios.py: hand-written
expectations of docs/protocol.md): the Python model and the C firmware (the ``chip_class``
fixture), and a chip of the vectorised `ChipArray` driven as a gateway drives it (its SYNC path is
its own code, everything else the model's)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from protocol.can import CanFrame, decode_can, make_id, to_can
from protocol.framing import DecodeError, decode_frame, encode, encode_frame
from protocol.messages import MESSAGE_TYPES, MsgType, Message, Sync, provisional_node
from protocol.scenarios import PROVISIONAL, UID
from protocol.vectors import build_vectors, message_from_fields
from virtual_sheet.chiparray import ChipArray

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
SCENARIOS = json.loads((VECTORS / "chip.json").read_text())["scenarios"]
CASES = [(sc, tr) for sc in SCENARIOS for tr in (("serial", "can") if sc["transport"] == "both" else (sc["transport"],))]


class _Sensor:
    def __init__(self, sc):
        self.xyz, self.status = tuple(sc["sensor"]["xyz"]), sc["sensor"]["status"]

    def __call__(self, now_s):
        return self.xyz, self.status

    def batch(self, now_s, idx):
        return np.tile(np.array(self.xyz, dtype=np.int64), (len(idx), 1)), np.full(len(idx), self.status, np.int64)


class _ArrayChip:
    """One chip of a ChipArray, dispatched as `virtual_sheet.gateway.Gateway` dispatches."""

    def __init__(self, uid, sensor, *, transport, capabilities):
        self.arr = ChipArray([uid], sensor.batch, transport=transport, capabilities=capabilities)
        self.can = transport == "can"

    def power_on(self, now):
        return self.arr.power_on(now)

    def poll(self, now):
        return self.arr.poll(now)

    def fault(self):
        self.arr.views[0].fault()

    def handle(self, frame, now):
        if self.can:
            d = decode_can(frame.arbitration_id, frame.data, is_fd=frame.is_fd)
        else:
            d = decode_frame(bytes(frame).rstrip(b"\x00"))
        if type(d) is Sync:
            return self.arr.sync(frame, d, now)
        if isinstance(d, Message) and d.node != 0:
            return self.arr.handle_node(d.node, frame, now, d)
        return self.arr.handle(frame, now, d)


def _make(kind, sc, transport):
    sensor = _Sensor(sc)
    uid = int(sc["uid"], 16)
    if kind == "array":
        return _ArrayChip(uid, sensor, transport=transport, capabilities=sc["capabilities"]), sensor
    return kind(uid, sensor, transport=transport, capabilities=sc["capabilities"]), sensor


def _frames(step, transport) -> list:
    if step["do"] == "send":
        msg = message_from_fields(step["type"], step["node"], step["fields"])
        return [to_can(msg) if transport == "can" else encode(msg)]
    if step["do"] == "send_raw":
        t, node, payload, v = step["type"], step["node"], bytes.fromhex(step["payload"]), step["version"]
        if transport == "can":
            prio = MESSAGE_TYPES[MsgType(t)].PRIORITY if t in MsgType._value2member_map_ else 4
            return [CanFrame(make_id(t, node, priority=prio, version=v), payload, False)]
        return [encode_frame(t, node, payload, version=v)]
    assert step["do"] == "send_wire" and transport == "serial"
    runs = bytes.fromhex(step["hex"]).split(b"\x00")[:-1]
    return [r + b"\x00" for r in runs if r]  # empty runs (0x00 0x00) are idle fill


def _decoded(frames, transport) -> list[dict]:
    out = []
    for f in frames:
        m = decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) if transport == "can" else decode_frame(f[:-1])
        assert not isinstance(m, DecodeError), f"the chip sent a frame that does not decode: {m}"
        out.append(m)
    return out


def _matches(got: list, expect: list[dict]) -> bool:
    if len(got) != len(expect):
        return False
    for m, e in zip(got, expect):
        if m.TYPE.name != e["type"] or m.node != e["node"]:
            return False
        for k, v in e["fields"].items():
            if getattr(m, k) != (pytest.approx(v) if isinstance(v, float) else v):
                return False
    return True


def run_scenario(kind, sc, transport) -> None:
    """Run one scenario; AssertionError naming the step that went wrong."""
    chip, sensor = _make(kind, sc, transport)
    for i, step in enumerate(sc["steps"]):
        at, do = step["at"], step["do"]
        where = f"{sc['name']} step {i} ({do} at {at})"
        if do not in ("power_on", "poll"):
            timers = _decoded(chip.poll(at), transport)
            assert _matches(timers, step.get("timers", [])), f"{where}: timers sent {timers}, " \
                                                             f"expected {step.get('timers', [])}"
        if do == "power_on":
            out = chip.power_on(at)
        elif do == "poll":
            out = chip.poll(at)
        elif do == "sensor":
            sensor.xyz, sensor.status = tuple(step["xyz"]), step["status"]
            out = []
        elif do == "sensor_fault":
            chip.fault()
            out = []
        else:
            out = []
            for f in _frames(step, transport):
                out += chip.handle(f, at)
        got = _decoded(out, transport)
        assert _matches(got, step["expect"]), f"{where}: sent {got}, expected {step['expect']}"


@pytest.mark.parametrize("sc,transport", CASES, ids=[f"{sc['name']}-{tr}" for sc, tr in CASES])
def test_a_chip_follows_the_scenario(chip_class, sc, transport):
    run_scenario(chip_class, sc, transport)


@pytest.mark.parametrize("sc,transport", CASES, ids=[f"{sc['name']}-{tr}" for sc, tr in CASES])
def test_the_chip_array_follows_the_scenario(sc, transport):
    run_scenario("array", sc, transport)


def test_the_checked_in_scenarios_are_the_generated_ones():
    assert json.loads((VECTORS / "chip.json").read_text()) == json.loads(json.dumps(build_vectors()["chip.json"]))


def test_the_provisional_ids_written_out_follow_the_formula():
    assert PROVISIONAL == tuple(provisional_node(UID, s) for s in range(len(PROVISIONAL)))


def test_a_wrong_expectation_is_caught():
    """The runner is not vacuous: one changed expected field fails it."""
    from virtual_sheet.chip import ChipModel
    sc = json.loads(json.dumps(next(s for s in SCENARIOS if s["name"] == "a_broadcast_is_never_nacked")))
    sc["steps"][-1]["expect"][0]["fields"]["rx_errors"] = 7
    with pytest.raises(AssertionError, match="step"):
        run_scenario(ChipModel, sc, "serial")


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_the_g_sensitivity_uses_the_nominal_2g_sensitivity(chip_class, transport):
    """§17.3 as 1.4 answers it (G05), on the wire of both reference chips: at ±4 g the accelerometer sends
    512 for 1 g (sensor: 1024 at ±2 g), so f_z = 512 · 2 / 1024 = 1 g; with Γ_zz = 0.01 rad/s per g and a
    still gyroscope the chip sends gz = round(−0.01 · 32.768 · 180/π) = round(−18.77) = −19 at ±1000 °/s.
    Read at the range's own nominal 2048/4 = 512 counts per g, f would be 2 g and gz −38."""
    from protocol.messages import (Ack, Assign, CalImuWrite, Capability, Config, ConfigImu, ImuSample, Start,
                                   ConfigImuFlag)
    uid = UID
    caps = int(Capability.MULTI_RANGE | Capability.CAN_FD) if transport == "can" else int(Capability.MULTI_RANGE)
    chip = chip_class(uid, lambda now_s: ((0, 0, 1024), 0), transport=transport, capabilities=caps,
                      sensors="accel+gyro", imu=lambda now_s, gr, mr: ((0, 0, 0), None, 0),
                      **({"fd": True} if transport == "can" else {}))
    p0 = provisional_node(uid, 0)

    def send(msg):
        f = to_can(msg) if transport == "can" else encode(msg)
        out = chip.handle(f, 0.1)
        if transport == "can":
            return [decode_can(o.arbitration_id, o.data, is_fd=o.is_fd) for o in out]
        return [decode_frame(bytes(o).rstrip(b"\x00")) for o in out]

    chip.power_on(0.0)
    assert send(Assign(p0, new_node=42, link=7, uid_low=uid & 0xFFFFFFFF)) == [Ack(42, MsgType.ASSIGN, 0)]
    assert send(CalImuWrite(42, 2, 8, 0, 0, 0.01)) == [Ack(42, MsgType.CAL_IMU_WRITE, 0)]  # Γ_zz
    assert send(Config(42, rate_hz=145, range=1, filter=0, heartbeat_ms=1000)) == [Ack(42, MsgType.CONFIG, 0)]
    fd = int(ConfigImuFlag.FD) if transport == "can" else 0
    assert send(ConfigImu(42, 1, 3, 0, fd)) == [Ack(42, MsgType.CONFIG_IMU, 0)]
    assert send(Start(42)) == [Ack(42, MsgType.START, 0)]
    (rec,) = send(Sync(counter=5))
    assert isinstance(rec, ImuSample) and (rec.x, rec.y, rec.z) == (0, 0, 512)
    assert rec.gyro == (0, 0, -19)
