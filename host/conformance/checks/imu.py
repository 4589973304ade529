"""Checks of 6/9-axis chips (docs §16) and their calibration (§17), and of a gateway packing IMU records
(§16.5)."""

from __future__ import annotations

import struct

from protocol.constants import SampleStatus
from protocol.messages import (cal_block_nominal, CAL_BLOCK_SIZE, CalBlock, CalImuData, CalImuRead,
                               CalImuWrite, Capability, ConfigImu, ConfigImuFlag, GatewayFlag, ImuSample,
                               MsgType, Nack, NackReason, Reset, Sample, SampleFormat, Stop, Sync,
                               TIME_UNKNOWN)

from ..session import acked, require, Session, Skip

from .gateway import a_chip_behind, packed_formats
from .registry import check


# ---------------------------------------------------------------------------------------------
# 6/9-axis chips (new in 1.2, §16): only on a chip whose INFO has GYRO
# ---------------------------------------------------------------------------------------------

def _imu_caps(s: Session) -> Capability:
    s.need_chip()
    caps = Capability(s.info.capabilities) if s.info is not None else Capability.NONE
    if not caps & Capability.GYRO:
        raise Skip("the chip's INFO has no GYRO capability: an accelerometer chip, §16 does not apply")
    return caps


def _config_imu(s: Session, fmt: int, gyro: int = 3, mag: int = 0, flags: int = 0) -> list:
    return s.request(ConfigImu(s.node, fmt, gyro, mag, flags))


def _nacked(ans, s: Session, reason: NackReason) -> bool:
    return any(isinstance(m, Nack) and m.node == s.node and m.command == MsgType.CONFIG_IMU and m.reason == reason
               for m in ans)


@check("16.2, 4.6, 8.2", "CONFIG_IMU: values out of range NACK BAD_VALUE, a sensor or CAN FD the chip lacks "
       "NACK UNSUPPORTED, refused while STREAMING (BAD_STATE), accepted in IDLE",
       "a host cannot select the 6/9-axis records, or selects one the chip cannot send",
       "check CONFIG_IMU's fields in §16.2's order before changing anything; ACK it in IDLE and FAULT")
def c_config_imu(s: Session):
    caps = _imu_caps(s)
    s.ensure_idle()
    for cfg in ((3, 3, 0), (1, 5, 0), (1, 3, 4)):
        ans = _config_imu(s, *cfg)
        require(_nacked(ans, s, NackReason.BAD_VALUE), f"CONFIG_IMU format/gyro/mag {cfg} answered {ans}")
    lacks = []
    if not caps & Capability.MAG:
        lacks.append(((2, 3, 0, 0), "format 2 without MAG"))
    if not caps & Capability.CAN_FD:
        lacks.append(((1, 3, 0, int(ConfigImuFlag.FD)), "flag FD without CAN_FD"))
    for cfg, why in lacks:
        ans = _config_imu(s, *cfg)
        require(_nacked(ans, s, NackReason.UNSUPPORTED), f"CONFIG_IMU {why} answered {ans}")
    fmt = 2 if caps & Capability.MAG else 1
    ans = _config_imu(s, fmt)
    require(acked(ans, s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} in IDLE answered {ans}")
    s.to_streaming()
    ans = _config_imu(s, 0)
    require(_nacked(ans, s, NackReason.BAD_STATE), f"CONFIG_IMU while STREAMING answered {ans}")
    require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
    ans = _config_imu(s, 0)
    require(acked(ans, s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format 0 in IDLE answered {ans}")
    return f"format {fmt} taken, {3 + len(lacks)} refusals as §16.2 orders them, BAD_STATE while STREAMING"


def _imu_round(s: Session, c: int) -> list:
    """SYNC ``c``: every answer of the chip to it, ``[(time, msg)]`` (records, and SAMPLEs that should not be)."""
    s.drain()
    s.port.send(Sync(counter=c))
    got = s.collect(s.answer_s, lambda ms: any(isinstance(m, (ImuSample, Sample)) and m.counter == c for m in ms))
    got += s.collect(min(0.05, s.timeout_s))  # a second answer to the same SYNC, if the chip sends one
    return [(t, m) for t, m in got if isinstance(m, (ImuSample, Sample))]


@check("16.3, 16.1, 5.1", "in format 1 or 2: every SYNC -> exactly one IMU record of that format with its counter; "
       "SATURATED exactly at the rails of every count; time_us −32768 iff the chip lacks SAMPLE_TIME, else within "
       "a SYNC period of the SYNC",
       "a host gets no gyroscope (or magnetometer), the wrong record, or sample times it cannot integrate with",
       "answer each SYNC with one IMU_SAMPLE (classic CAN: §16.4's frames) of the configured format; set "
       "SATURATED from the counts sent; send time_us (µs after the SYNC) or −32768 without SAMPLE_TIME")
def c_imu_records(s: Session):
    caps = _imu_caps(s)
    if s.sync_gateway is not None or s.packing_gateway:
        raise Skip("behind a gateway that drives SYNC or packs: the records are the gateway's business (§16.5)")
    s.ensure_idle()
    fmt = 2 if caps & Capability.MAG else 1
    require(acked(_config_imu(s, fmt), s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} refused")
    s.to_streaming()
    timed = bool(caps & Capability.SAMPLE_TIME)
    seen = []
    for c in range(300, 316):
        ans = _imu_round(s, c)
        mine = [m for _, m in ans if m.counter == c]
        require(len(mine) == 1 and isinstance(mine[0], ImuSample),
                f"SYNC 0x{c:04X} answered {[m for _, m in ans][:3]} (one IMU record of format {fmt})")
        m = mine[0]
        require(m.format == fmt, f"SYNC 0x{c:04X}: a format-{int(m.format)} record after CONFIG_IMU format {fmt}")
        counts = (m.x, m.y, m.z)
        rails = any(v in (-2048, 2047) for v in counts) or any(v in (-32768, 32767) for v in m.gyro + (m.mag or ()))
        require(rails == bool(m.status & SampleStatus.SATURATED),
                f"SATURATED {'clear' if rails else 'set'} for accel {counts}, gyro {m.gyro}, mag {m.mag}")
        if timed:
            require(m.time_us != TIME_UNKNOWN, f"time_us unknown (−32768) from a chip with SAMPLE_TIME (§16.1)")
            require(abs(m.time_us) <= 1e6 / 145 + 2000,
                    f"time_us {m.time_us} µs: more than a SYNC period (145 Hz) from its SYNC")
        else:
            require(m.time_us == TIME_UNKNOWN, f"time_us {m.time_us} from a chip without SAMPLE_TIME: −32768 (§16.1)")
        seen.append(m)
    require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
    require(acked(_config_imu(s, 0), s.node, MsgType.CONFIG_IMU), "CONFIG_IMU format 0 refused")
    last = seen[-1]
    return (f"{len(seen)} records of format {fmt}; last accel {(last.x, last.y, last.z)}, gyro {last.gyro}"
            + (f", mag {last.mag}" if last.mag else "") + f", time_us {last.time_us}")


@check("16.4, 7.2", "classic CAN: a record as IMU_GYRO (IMU_MAG) IMU_ACCEL, in that order, back to back, "
       "each 8 bytes, one counter", "a receiver cannot assemble the records (it reports them incomplete)",
       "send the frames of §16.4 in their order with the record's counter (IMU_ACCEL: its low byte)",
       transport="can")
def c_imu_can_frames(s: Session):
    caps = _imu_caps(s)
    if s.sync_gateway is not None or s.packing_gateway:
        raise Skip("behind a gateway that drives SYNC or packs (§16.5)")
    fmt = 2 if caps & Capability.MAG else 1
    s.ensure_idle()
    require(acked(_config_imu(s, fmt), s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} refused")
    s.to_streaming()
    s.port.raw.clear()
    for c in range(400, 408):
        _imu_round(s, c)
    require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
    require(acked(_config_imu(s, 0), s.node, MsgType.CONFIG_IMU), "CONFIG_IMU format 0 refused")
    want = [MsgType.IMU_GYRO] + ([MsgType.IMU_MAG] if fmt == 2 else []) + [MsgType.IMU_ACCEL]
    seq = [(t, aid, d) for aid, d, _fd in s.port.raw for t in [(aid >> 20) & 0x3F]
           if (aid & 0xFFFF) == s.node and t in (MsgType.IMU_GYRO, MsgType.IMU_MAG, MsgType.IMU_ACCEL, MsgType.IMU_SAMPLE)]
    require(bool(seq), "no IMU frame from the chip")
    types = [t for t, _, _ in seq]
    require(len(types) % len(want) == 0 and all(types[i:i + len(want)] == want for i in range(0, len(types), len(want))),
            f"frame types {[MsgType(t).name for t in types[:6]]}: §16.4 sends {[w.name for w in want]} per record")
    for i in range(0, len(seq), len(want)):
        grp = seq[i:i + len(want)]
        require(all(len(d) == 8 for _, _, d in grp), f"IMU frames of {[len(d) for _, _, d in grp]} bytes, not 8")
        ctr = grp[0][2][0] | grp[0][2][1] << 8
        require(all((d[0] | d[1] << 8) == ctr for _, _, d in grp[1:-1]) and grp[-1][2][0] == ctr & 0xFF,
                f"a record's frames carry different counters: {[d.hex() for _, _, d in grp]}")
    return f"{len(seq) // len(want)} records, {len(want)} frames each, in order"


def _cal_imu_nack(ans, s: Session, t: MsgType) -> bool:
    return ans == [Nack(s.node, t, NackReason.UNSUPPORTED)]


def _cal_imu_value(block: int, index: int) -> float:
    """A distinct float32 per element for check 45: a −0, a subnormal, large and small magnitudes."""
    if (block, index) == (CalBlock.GYRO_G_SENS, 4):
        return -0.0
    if (block, index) == (CalBlock.MAG_HARD_IRON, 2):
        return 1e-40  # subnormal in binary32
    return float(struct.unpack("<f", struct.pack("<f", (-1) ** index * (block + 1) * (index + 3) * 1.25e-3))[0])


@check("17.2, 17.1, 17.3", "CAL_IMU_WRITE then CAL_IMU_READ gives every gyroscope (and magnetometer) calibration "
       "element back bit for bit with its stored flag, and the chip applies it (a zero matrix sends zero counts); "
       "a chip without the sensor answers both with NACK 5 UNSUPPORTED (a chip answering both NACK 1, one of 1.2 or "
       "earlier, is skipped)",
       "a host cannot store the gyroscope's or magnetometer's calibration on the chip, or gets another back",
       "keep the CAL_IMU_WRITE value per element as given (binary32, −0 and subnormals included), answer "
       "CAL_IMU_READ with CAL_IMU_DATA carrying it; apply §17.3 to the counts sent; NACK 5 for a block whose "
       "sensor the chip lacks")
def c_cal_imu(s: Session):
    s.need_chip()
    caps = Capability(s.info.capabilities) if s.info is not None else Capability.NONE
    s.ensure_idle()
    have = [b for b in CalBlock if caps & (Capability.GYRO if b <= CalBlock.GYRO_G_SENS else Capability.MAG)]
    lacks = [b for b in (CalBlock.GYRO_BIAS, CalBlock.MAG_MATRIX) if b not in have]
    # §17.2, §12: a chip of 1.2 or earlier does not know the types (NACK 1, §8.1), and the wire carries no
    # minor version to tell it from a 1.3 chip: both types NACK 1 is such a chip, to which §17 does not apply
    probe = (have or lacks)[0]
    ans = s.request(CalImuRead(s.node, probe, 0))
    if ans == [Nack(s.node, MsgType.CAL_IMU_READ, NackReason.UNKNOWN_COMMAND)]:
        ans = s.request(CalImuWrite(s.node, probe, 0, 0, 0, cal_block_nominal(probe, 0)))  # nominal: changes nothing
        require(ans == [Nack(s.node, MsgType.CAL_IMU_WRITE, NackReason.UNKNOWN_COMMAND)],
                f"CAL_IMU_READ answered NACK 1 UNKNOWN_COMMAND (a chip of 1.2 or earlier) but CAL_IMU_WRITE {ans} "
                f"(§17.2, §8.1: a chip knows both types or neither)")
        raise Skip("CAL_IMU_READ and CAL_IMU_WRITE answered NACK 1 UNKNOWN_COMMAND: a chip of protocol 1.2 or "
                   "earlier, which does not know them (§17.2, §12); §17 does not apply")
    for b in lacks:
        ans = s.request(CalImuRead(s.node, b, 0))
        require(_cal_imu_nack(ans, s, MsgType.CAL_IMU_READ), f"CAL_IMU_READ block {int(b)} without its sensor "
                                                               f"answered {ans} (§17.2: NACK 5)")
        ans = s.request(CalImuWrite(s.node, b, 0, 0, 0, 0.5))
        require(_cal_imu_nack(ans, s, MsgType.CAL_IMU_WRITE), f"CAL_IMU_WRITE block {int(b)} without its sensor "
                                                                f"answered {ans} (§17.2: NACK 5)")
    if not have:
        return "no gyroscope, no magnetometer: CAL_IMU_READ and CAL_IMU_WRITE answered NACK 5"
    elements = [(b, i) for b in have for i in range(CAL_BLOCK_SIZE[b])]
    try:
        for b, i in elements:
            ans = s.request(CalImuWrite(s.node, b, i, 0, 0, _cal_imu_value(b, i)))
            require(acked(ans, s.node, MsgType.CAL_IMU_WRITE), f"CAL_IMU_WRITE block {int(b)} index {i} answered {ans}")
        for b, i in elements:
            ans = s.request(CalImuRead(s.node, b, i))
            want = struct.pack("<f", _cal_imu_value(b, i))
            require(len(ans) == 1 and isinstance(ans[0], CalImuData) and (ans[0].block, ans[0].index) == (b, i)
                    and ans[0].flags & 1 == 0 and struct.pack("<f", ans[0].value) == want,
                    f"CAL_IMU_READ block {int(b)} index {i} answered {ans} (written: {want.hex()}, not stored)")
        applied = "not checked behind a gateway that drives SYNC or packs"
        if s.sync_gateway is None and not s.packing_gateway:
            for b in have:  # zero matrices: every gyroscope (and magnetometer) count sent is 0 (§17.3)
                if b in (CalBlock.GYRO_MATRIX, CalBlock.MAG_MATRIX):
                    for i in range(9):
                        require(acked(s.request(CalImuWrite(s.node, b, i, 0, 0, 0.0)), s.node, MsgType.CAL_IMU_WRITE),
                                "CAL_IMU_WRITE refused")
            fmt = 2 if caps & Capability.MAG else 1
            require(acked(_config_imu(s, fmt), s.node, MsgType.CONFIG_IMU), f"CONFIG_IMU format {fmt} refused")
            s.to_streaming()
            recs = []
            for c in range(500, 504):
                recs += [m for _, m in _imu_round(s, c) if isinstance(m, ImuSample) and m.counter == c]
            require(acked(s.request(Stop(s.node)), s.node, MsgType.STOP), "STOP refused")
            require(acked(_config_imu(s, 0), s.node, MsgType.CONFIG_IMU), "CONFIG_IMU format 0 refused")
            require(len(recs) == 4, f"{len(recs)} IMU records for 4 SYNCs")
            bad = [m for m in recs if m.gyro != (0, 0, 0) or (fmt == 2 and m.mag != (0, 0, 0))]
            require(not bad, f"with zero matrices the chip sent gyro {bad[0].gyro if bad else ''}"
                             f"{', mag ' + str(bad[0].mag) if bad and fmt == 2 else ''} (§17.3: 0)")
            applied = "zero matrices applied (4 records of zeros)"
    finally:  # leave the chip as it was: every element nominal, not stored
        s.ensure_idle()
        for b, i in elements:
            s.request(CalImuWrite(s.node, b, i, 0, 0, cal_block_nominal(b, i)))
    return (f"{len(elements)} elements read back bit for bit; {applied}"
            + (f"; blocks {[int(b) for b in lacks]} without their sensor: NACK 5" if lacks else ""))



@check("16.5, 13.2, 13.1, 16.1", "packing IMU records (sample_format 1 or 2): every SYNC a chip answered -> "
       "SNAPSHOT_IMU frames of that format with every link of the runs once, in order, from the gateway; links "
       "not heard INVALID records; the chip's own records not passed on",
       "the host loses a 6/9-axis sheet's links or reads them in the wrong format: the gateway did not configure "
       "its chips, packed the wrong record size, or passed records on beside its SNAPSHOT_IMU",
       "configure your chips to the GATEWAY_INFO sample_format (CONFIG_IMU) before passing START on; answer SYNC "
       "with SNAPSHOT_IMU frames of that format covering each run once, ascending, at most 77/53 (serial) or 4/3 "
       "(CAN FD) records each; a link not heard by 10 ms: INVALID, counts 0, time_us -32768; pass no record "
       "of a covered link on", profiles=("gateway",))
def c_gateway_packing_imu(s: Session):
    from protocol.can import MAX_FD_IMU_RECORDS
    from protocol.messages import MAX_SERIAL_IMU_RECORDS, ImuAccel, ImuGyro, ImuMag, SnapshotImu
    s.assign_gateway()
    g = s.gateways[s.uid]
    if not g.flags & GatewayFlag.PACKING:
        raise Skip("the gateway does not pack (GATEWAY_INFO flag PACKING clear)")
    fmts = packed_formats(g)
    if fmts <= {SampleFormat.ACCEL_12}:
        raise Skip("the gateway packs SAMPLEs (GATEWAY_INFO sample_format 0): check 38's")
    require(len(fmts) == 1 and fmts <= {1, 2}, f"GATEWAY_INFO sample_format {sorted(fmts)}: one of 1, 2 (§16.5)")
    fmt = SampleFormat(fmts.pop())
    uid, chip_node, link = a_chip_behind(s)
    runs = sorted((r.first_link, r.link_count) for r in g.runs.values() if r.link_count)
    cap = (MAX_SERIAL_IMU_RECORDS if s.port.kind == "serial" else MAX_FD_IMU_RECORDS)[fmt]
    want_links = [a + k for a, n in runs for k in range(n)]
    unpacked = (Sample, ImuSample, ImuGyro, ImuMag, ImuAccel)
    try:
        for c in range(40, 43):
            s.drain()
            if not g.flags & GatewayFlag.SYNC_SOURCE:
                s.port.send(Sync(counter=c))
            got, passed = [], []
            deadline = s.port.now() + s.answer_s
            while s.port.now() < deadline:
                item = s.port.next(deadline)
                if item is None:
                    break
                s.note(*item)
                m = item[1]
                if isinstance(m, SnapshotImu) and m.node == s.node:
                    got.append(m)
                    if sum(x.count for x in got if x.counter == got[0].counter) >= len(want_links):
                        break
                elif isinstance(m, unpacked) and m.node == chip_node:
                    passed.append(m)
            require(bool(got), f"§16.5: SYNC 0x{c:04X} (the chip on link {link} streams) answered with no "
                               f"SNAPSHOT_IMU from the gateway's node 0x{s.node:04X}"
                               + (f"; the chip's {type(passed[0]).__name__} was passed on" if passed else ""))
            c0 = got[0].counter
            frames = [x for x in got if x.counter == c0]
            require(all(x.format == fmt for x in frames),
                    f"§16.5: SNAPSHOT_IMU of format {sorted({int(x.format) for x in frames})}, GATEWAY_INFO says {int(fmt)}")
            covered = [(x.first_link, x.count) for x in frames]
            require(all(n <= cap for _, n in covered), f"§16.5: a SNAPSHOT_IMU over {cap} records: {covered}")
            links = [x.first_link + k for x in frames for k in range(x.count)]
            require(links == want_links, f"§13.2: SNAPSHOT_IMU frames of counter 0x{c0:04X} cover links "
                                         f"{covered}, the runs are {runs} (each link once, ascending)")
            require(not passed, f"§13.1: the chip's own {type(passed[0]).__name__ if passed else ''} (link {link}) "
                                f"was passed on beside the SNAPSHOT_IMU that packs its link")
            for x in frames:
                counts, status, t_us, gyro, mag = x.arrays()
                for k in range(x.count):
                    ln = x.first_link + k
                    st = int(status[k])
                    if ln == link:
                        require(not st & SampleStatus.INVALID,
                                f"§16.5: the streaming chip's link {ln} is INVALID (the gateway did not get its "
                                f"record: did it configure the chip to format {int(fmt)}?)")
                    else:
                        zero = (counts[k].tolist() == [0, 0, 0] and gyro[k].tolist() == [0, 0, 0]
                                and (mag is None or mag[k].tolist() == [0, 0, 0]))
                        require(st & SampleStatus.INVALID and zero and int(t_us[k]) == TIME_UNKNOWN,
                                f"§16.1: link {ln} (no chip streams there) is status 0x{st:X}, counts "
                                f"{counts[k].tolist()}, gyro {gyro[k].tolist()}, time_us {int(t_us[k])}: not an "
                                f"INVALID record (zeros, time_us -32768)")
    finally:
        s.port.send(Stop(chip_node))
        s.port.send(Reset(chip_node))
        s.collect(s.timeout_s)
    return (f"format {int(fmt)}, runs {runs}: every link once per counter; the chip on link {link} valid, the rest "
            f"INVALID records; no record passed on")
