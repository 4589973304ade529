"""The C firmware's chip (firmware_ref/src/chip.c via `CFirmwareChip`) against the state table.

Two ways:
* the chip suite (tests/virtual_sheet/test_chip.py: every (state, type) pair of protocol/state.py
  RULES on both transports, NACK reasons, timers, counters) runs with ``chip_class`` = `CFirmwareChip`
  as one of its fixture parameters — one suite, two back ends;
* hypothesis drives the C chip and the Python chip with the same random frame sequences (valid
  commands, damaged frames, time steps) and requires the same answers, frame for frame — as
  accelerometer chips and as 6/9-axis chips (docs §16: CONFIG_IMU, IMU records on every transport).
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.can import CanFrame, decode_can, make_id, to_can
from protocol.framing import DecodeError, decode_frame, encode, encode_frame
from protocol.messages import (Assign, CalImuRead, CalImuWrite, CalRead, CalWrite, ChipState, Config, ConfigImu, GetInfo, Info, MsgType,
                               Reset, Start, Stop, Sync)

pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
from firmware_ref.chip import CFirmwareChip  # noqa: E402
from virtual_sheet.chip import ChipModel  # noqa: E402

import tests.virtual_sheet.test_chip as base  # noqa: E402

UID = base.UID
NODE = base.NODE


def test_the_chip_suite_runs_the_c_chip_too():
    from tests.conftest import _chip_class_params

    assert [p.values[0] for p in _chip_class_params()] == [ChipModel, CFirmwareChip]
    assert isinstance(base.Driver(CFirmwareChip).chip, CFirmwareChip)


# ---------------------------------------------------------------------------------------------
# differential: C chip == Python chip on the same random input
# ---------------------------------------------------------------------------------------------

def _sensor(now_s):
    k = int(now_s * 64)  # the scripts' time step: every sample differs; now and then the ADC fails
    return ((k * 37) % 4096 - 2048, (k * 11) % 4096 - 2048, 1000 - k % 50), (8 if k % 7 == 5 else k % 3)


def _imu(now_s, gyro_range, mag_range):
    """A gyroscope and magnetometer that move with time, at their rails now and then (SATURATED),
    latched up to 3 ms either side of the SYNC."""
    k = int(now_s * 64)
    g = ((k * 4099) % 65536 - 32768, -(k * 97 % 30000) >> gyro_range, 32767 if k % 11 == 3 else k)
    m = (8192 >> mag_range, -32768 if k % 13 == 7 else -4096, k % 100)
    return g, m, (k * 37) % 6001 - 3000


def _normalise(frames, transport):
    """Decoded frames, INFO's firmware version masked (the two firmwares differ there only)."""
    out = []
    for f in frames:
        m = decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) if transport == "can" else decode_frame(f[:-1])
        assert not isinstance(m, DecodeError), m
        if isinstance(m, Info):
            m = Info(m.node, 0, 0, 0, m.protocol_version, m.capabilities, m.adc_bits, m.state)
        out.append(m)
    return out


def _command(draw, transport):
    """One frame from the host — a valid command, an odd one, or damage — as a function of the
    chip's current node (so "addressed to the chip" follows its node through ASSIGN and RESET)."""
    target = draw(st.sampled_from(["chip", "chip", "chip", "broadcast", "other"]))
    kind = draw(st.sampled_from(["assign", "assign", "config", "start", "stop", "sync", "sync", "sync", "get_info",
                                 "reset", "cal_write", "cal_read", "raw", "damaged", "config_imu", "config_imu",
                                 "cal_imu_write", "cal_imu_write", "cal_imu_read"]))
    uid_low = draw(st.sampled_from([UID & 0xFFFFFFFF, UID & 0xFFFFFFFF, 0xDEADBEEF]))
    new_node = draw(st.sampled_from([1, 42, 0x7FFF]))
    link = draw(st.integers(0, 300))
    cfg = (draw(st.sampled_from([0, 1, 145, 4000, 4001])), draw(st.integers(0, 4)), draw(st.integers(0, 4)),
           draw(st.sampled_from([0, 250, 500, 1000])))
    counter = draw(st.sampled_from([0, 1, 2, 3, 10, 0x7FFF, 0xFFFE, 0xFFFF]))
    cal = (draw(st.integers(0, 2)), draw(st.integers(0, 3)), draw(st.integers(-40, 40)),
           draw(st.sampled_from([1000.0, 1024.5])))
    imu = (draw(st.sampled_from([0, 1, 2, 2, 3])), draw(st.sampled_from([0, 3, 4, 5])), draw(st.sampled_from([0, 1, 3, 4])),
           draw(st.sampled_from([0, 0, 1, 2])))
    # v1.3 (§17): elements whose corrected counts land near integers (never near a half), so binary32
    # on the C chip and binary64 in Python round alike: matrices of small integers, a bias of 100
    # counts at ±1000 °/s (an even count at every range), a hard iron of 1 gauss
    block = draw(st.integers(0, 4))
    index = draw(st.integers(0, 2 if block in (1, 4) else 8))
    value = {0: draw(st.sampled_from([1.0, 2.0, -1.0, 0.0])), 1: draw(st.sampled_from([0.0, 100 / 1877.4681031])),
             2: 0.0, 3: draw(st.sampled_from([1.0, -1.0, 2.0, 0.0])), 4: draw(st.sampled_from([0.0, 1e-4]))}[block]
    cal_imu = (block, index, draw(st.integers(0, 1)), 0, value)
    # 0x0D: a node -> host type (IMU_SAMPLE); 0x19 CONFIG_IMU, 0x1A CAL_IMU_WRITE of any length; 0x1C: undefined in v1.3
    raw_type = draw(st.sampled_from([0x03, 0x0D, 0x10, 0x11, 0x12, 0x13, 0x17, 0x18, 0x19, 0x1A, 0x1B, 0x1C, 0x3F]))
    payload = draw(st.binary(max_size=9))
    version = draw(st.sampled_from([1, 1, 2]))
    is_fd = draw(st.booleans())
    flip = (draw(st.integers(0, 30)), draw(st.integers(1, 255)))

    def make(chip_node):
        n = {"chip": chip_node, "broadcast": 0, "other": 0x1234}[target]
        if kind == "assign":
            msg = Assign(n or 1, new_node=new_node, link=link, uid_low=uid_low)
        elif kind == "config":
            msg = Config(n, *cfg)
        elif kind == "start":
            msg = Start(n)
        elif kind == "stop":
            msg = Stop(n)
        elif kind == "sync":
            msg = Sync(counter=counter)
        elif kind == "get_info":
            msg = GetInfo(n)
        elif kind == "reset":
            msg = Reset(n)
        elif kind == "cal_write":
            msg = CalWrite(n or 1, *cal)
        elif kind == "cal_read":
            msg = CalRead(n or 1, axis=cal[0])
        elif kind == "config_imu":
            msg = ConfigImu(n, *imu)
        elif kind == "cal_imu_write":
            msg = CalImuWrite(n or 1, *cal_imu)
        elif kind == "cal_imu_read":
            msg = CalImuRead(n or 1, *cal_imu[:2])
        elif transport == "can":
            return CanFrame(make_id(raw_type, n, priority=4, version=version), payload, is_fd)
        else:
            frame = encode_frame(raw_type, n, payload, version=version)
            if kind == "damaged":
                b = bytearray(frame)
                b[flip[0] % (len(b) - 1)] ^= flip[1]
                frame = bytes(b)
            return frame
        return to_can(msg) if transport == "can" else encode(msg)

    return make


@st.composite
def _scripts(draw, transport):
    steps = []
    for _ in range(draw(st.integers(1, 40))):
        # time steps in 1/64 s: exact in float seconds and in integer microseconds alike, so the
        # Python chip's float deadlines and the C chip's microsecond deadlines fall identically
        dt = draw(st.sampled_from([0, 0, 1, 6, 16, 64, 160])) / 64
        steps.append((dt, _command(draw, transport)))
    return steps


def _late_fault_sensor(now_s):
    """Valid readings (rails now and then) until k = 36, then an ADC failure (INVALID)."""
    (x, y, z), st = _sensor(now_s)
    return (x, y, z), (8 if int(now_s * 64) >= 36 else st & 3)


def _run_both(steps, transport, fd, capabilities, sensors="accel", sensor=_sensor):
    imu = _imu if sensors != "accel" else None
    chips = [cls(UID, sensor, transport=transport, fd=fd, capabilities=capabilities, sensors=sensors, imu=imu)
             for cls in (ChipModel, CFirmwareChip)]
    t = 0.0
    outs = [_normalise(c.power_on(t), transport) for c in chips]
    assert outs[0] == outs[1]
    states = set()
    for dt, frame in steps:
        t += dt
        if callable(frame):
            frame = frame(chips[0].node)
        if isinstance(frame, bytes) and frame.count(b"\x00") != 1:
            continue  # damage made two frames of one: `handle` takes one frame (devices split at 0x00)
        got = []
        for c in chips:
            out = c.poll(t)
            out += c.handle(frame, t)
            got.append(_normalise(out, transport))
        assert got[0] == got[1], (frame, t)
        assert (chips[0].state, chips[0].node, chips[0].link, chips[0].rx_errors, chips[0].missed_syncs) == \
               (chips[1].state, chips[1].node, chips[1].link, chips[1].rx_errors, chips[1].missed_syncs)
        states.add(chips[0].state)
    return states


@settings(max_examples=120)
@given(st.data(), st.sampled_from(["serial", "can"]), st.booleans(), st.sampled_from([0, 0x3C, 0x08, 0x10]))
def test_c_chip_answers_exactly_as_the_python_chip(data, transport, fd, caps):
    steps = data.draw(_scripts(transport))
    _run_both(steps, transport, fd and transport == "can", caps)


@settings(max_examples=150)
@given(st.data(), st.sampled_from(["serial", "can"]), st.booleans(), st.sampled_from([0, 0x3C]),
       st.sampled_from(["accel+gyro", "accel+gyro+mag"]))
def test_a_6_or_9_axis_c_chip_answers_exactly_as_the_python_chip(data, transport, fd, caps, sensors):
    """CONFIG_IMU's checks and states, and every SYNC's record — IMU_SAMPLE, classic frames, CAN FD —
    frame for frame as the Python model, with SATURATED from the gyroscope's and magnetometer's rails."""
    steps = data.draw(_scripts(transport))
    _run_both(steps, transport, fd and transport == "can", caps, sensors)


def test_a_6_and_9_axis_lifecycle_reaches_every_record_on_both_chips_identically():
    """Deterministic: CONFIG_IMU format 1 then 2 (classic CAN and FD), SYNCs with rails, an INVALID
    record from a failed conversion (FAULT), RESET back to format 0."""
    for transport, fd in (("serial", False), ("can", False), ("can", True)):
        w = (lambda m: to_can(m)) if transport == "can" else encode
        steps = [(0.0, lambda n: w(Assign(n, new_node=NODE, link=5, uid_low=UID & 0xFFFFFFFF))),
                 (0.0, w(ConfigImu(NODE, 1, 4, 0, 0))), (0.0, w(Start(0)))]
        steps += [(1 / 64, w(Sync(counter=c))) for c in range(1, 4)]
        steps += [(0.0, w(Stop(NODE))), (0.0, w(ConfigImu(NODE, 2, 2, 3, int(fd)))), (0.0, w(Start(NODE)))]
        steps += [(1 / 64, w(Sync(counter=c))) for c in range(4, 40)]
        steps += [(0.0, w(Reset(NODE))), (2.0, w(GetInfo(0)))]
        assert _run_both(steps, transport, fd, 0x3C, "accel+gyro+mag", _late_fault_sensor) == set(ChipState)


def test_walk_through_the_lifecycle_on_both_chips_identically():
    """A deterministic script that reaches every state (BOOT, IDLE, STREAMING, FAULT via a bad sample)."""
    for transport in ("serial", "can"):
        w = (lambda m: to_can(m)) if transport == "can" else encode
        chip = CFirmwareChip(UID, _sensor, transport=transport)
        chip.power_on(0.0)
        prov = chip.node
        steps = [(0.0, w(Assign(prov, new_node=NODE, link=5, uid_low=UID & 0xFFFFFFFF))),
                 (0.0, w(Config(NODE, heartbeat_ms=250))), (0.0, w(CalWrite(NODE, axis=1, flags=1, offset_q4=3))),
                 (0.0, w(CalRead(NODE, axis=1))), (0.0, w(Start(0)))]
        steps += [(1 / 64, w(Sync(counter=c))) for c in range(1, 120)]
        steps += [(0.5, w(GetInfo(0))), (0.0, w(Stop(NODE))), (0.0, w(Reset(NODE))), (2.0, w(GetInfo(0)))]
        assert _run_both(steps, transport, False, 0x3C) == set(ChipState)


def test_the_c_chip_applies_any_gyro_and_mag_calibration_within_one_count_of_the_python_chip():
    """§17.3: the C chip computes in fixed point, the Python model in binary64; a chip may be off by
    one count from the exact result. Random (seeded) calibrations of realistic size and readings over
    the whole range, at every gyro and mag range and two accelerometer ranges."""
    import numpy as np

    from protocol.messages import ImuSample, provisional_node

    rng = np.random.Generator(np.random.MT19937(29))
    worst = changed = 0
    for trial in range(40):
        readings = rng.integers(-32768, 32768, size=(2, 3))
        accel = rng.integers(-2048, 2048, size=3)
        chips = [cls(UID, lambda t, a=tuple(int(v) for v in accel): (a, 0), transport="serial",
                     capabilities=0x3C, sensors="accel+gyro+mag",
                     imu=lambda t, g, m, r=readings: (tuple(int(v) for v in r[0]), tuple(int(v) for v in r[1]), 0))
                 for cls in (ChipModel, CFirmwareChip)]
        cal = {0: np.eye(3) + rng.normal(0, 0.02, (3, 3)), 1: rng.normal(0, 0.02, 3),
               2: rng.normal(0, 3e-4, (3, 3)), 3: np.eye(3) + rng.normal(0, 0.1, (3, 3)), 4: rng.normal(0, 2e-5, 3)}
        gr, mr, ar = int(rng.integers(0, 5)), int(rng.integers(0, 4)), int(rng.integers(0, 2))
        recs = []
        for c in chips:
            c.power_on(0.0)
            c.handle(encode(Assign(provisional_node(UID, 0), new_node=NODE, link=0, uid_low=UID & 0xFFFFFFFF)), 0.0)
            for b, v in cal.items():
                for i, x in enumerate(np.ravel(v).tolist()):
                    c.handle(encode(CalImuWrite(NODE, b, i, 0, 0, x)), 0.0)
            c.handle(encode(Config(NODE, range=ar)), 0.0)
            c.handle(encode(ConfigImu(NODE, 2, gr, mr, 0)), 0.0)
            c.handle(encode(Start(NODE)), 0.0)
            (rec,) = [m for m in _normalise(c.handle(encode(Sync(counter=trial)), 0.01), "serial")
                      if isinstance(m, ImuSample)]
            recs.append(rec)
        a, b = recs
        assert (a.x, a.y, a.z, a.time_us) == (b.x, b.y, b.z, b.time_us)
        d = np.abs(np.subtract(a.gyro + a.mag, b.gyro + b.mag))
        worst = max(worst, int(d.max()))
        changed += a.gyro != tuple(readings[0]) and a.mag != tuple(readings[1])
        assert d.max() <= 1, (trial, a, b)
    assert worst <= 1 and changed >= 35  # (the calibrations did change what was sent)
