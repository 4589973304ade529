"""Deliberately broken nodes ("mutants"): each breaks one MUST of docs/protocol.md, so the conformance
suite must fail it — and only in the checks that hold a node to that rule
(tests/host/conformance/test_mutants.py).

* Chips on the Python chip model: each subclasses `ChipModel` (whose behaviour is not changed) and
  rewrites what it hears or sends (`MUTANTS`).
* The same breakages in the C firmware: its test build (-DCAPSHEET_MUTANTS, the cffi module
  ``firmware_ref._capsheet_fw_mutants``) breaks the rule a chip's ``mutant`` field names
  (`C_MUTANTS` maps them to the Python mutants whose expected failures they share); the QEMU port
  builds three of them (``make -C firmware_ref qemu MUTANT=``).
* Gateways: subclasses of the virtual `Gateway` (`GATEWAY_MUTANTS`), for the gateway profile.
* Healthy variants (`HEALTHY`): nodes the suite must pass — noise-free, a quiet 12-bit sensor, a
  packing gateway in front, several chips on one port, a SYNC-source gateway, gateways that flush
  anywhere in the 10 ms §13.2 allows, and 6/9-axis chips behind gateways packing SNAPSHOT_IMU.
"""

from __future__ import annotations

import binascii

from cobs import cobs

from protocol.can import CanFrame, decode_can, make_id, split_id, to_can
from protocol.framing import DecodeError, decode_frame, encode
from protocol.messages import (Ack, Assign, Capability, ChipState, Config, Direction, ImuSample, Info, MsgType, Nack,
                               NackReason, Reset, Sample, Start, Stop, Sync)
from virtual_sheet.chip import ChipModel, frame_header
from virtual_sheet.gateway import Gateway, GatewayNode

__all__ = ["MUTANTS", "HEALTHY", "FlushesAt5ms", "FlushesAt10ms"]


class _Rewriting(ChipModel):
    """Passes every frame the model sends through ``rewrite(msg) -> msg | list | None``."""

    def rewrite(self, msg):
        return msg

    def _emit(self, out):
        res = []
        for f in out:
            m = decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) if isinstance(f, CanFrame) \
                else decode_frame(bytes(f).rstrip(b"\x00"))
            if isinstance(m, DecodeError):
                res.append(f)
                continue
            new = self.rewrite(m)
            for n in ([] if new is None else new if isinstance(new, list) else [new]):
                res.append(n if isinstance(n, (bytes, CanFrame)) else (to_can(n) if self._can else encode(n)))
        return res

    def handle(self, frame, now_s, decoded=None):
        return self._emit(super().handle(frame, now_s, decoded))

    def poll(self, now_s):
        return self._emit(super().poll(now_s))

    def power_on(self, now_s):
        return self._emit(super().power_on(now_s))


class DeadSensor(ChipModel):
    """The accelerometer reads (0, 0, 0) with status OK: a dead sensor reported healthy."""

    def __init__(self, uid, sensor, **kw):
        super().__init__(uid, lambda now_s: ((0, 0, 0), 0), **kw)


class FrozenSample(_Rewriting):
    """Converts once: every later SAMPLE repeats the first one's counts and status, unflagged (§5.3) —
    also after a range change, which a real conversion would show."""

    def rewrite(self, m):
        if isinstance(m, Sample):
            first = getattr(self, "_frozen", None)
            if first is None:
                self._frozen = first = (m.x, m.y, m.z, m.status)
            return Sample(m.node, m.counter, *first)
        return m


class WrongCrc(ChipModel):
    """CRC-16/XMODEM (init 0x0000) instead of CRC-16/CCITT-FALSE (init 0xFFFF) on every frame."""

    def _fix(self, out):
        res = []
        for f in out:
            body = cobs.decode(bytes(f).rstrip(b"\x00"))[:-2]
            res.append(cobs.encode(body + binascii.crc_hqx(body, 0).to_bytes(2, "big")) + b"\x00")
        return res

    def handle(self, frame, now_s, decoded=None):
        return self._fix(super().handle(frame, now_s, decoded))

    def poll(self, now_s):
        return self._fix(super().poll(now_s))

    def power_on(self, now_s):
        return self._fix(super().power_on(now_s))


class WrongCrcOnSamples(ChipModel):
    """A wrong CRC (XMODEM) on every SAMPLE, the right one on everything else (§6.2): a port does not
    damage one message type only — the suite must blame the chip, not the port."""

    def _sample(self, counter, now_s):
        f = super()._sample(counter, now_s)
        if self._can:
            return f
        body = cobs.decode(bytes(f).rstrip(b"\x00"))[:-2]
        return cobs.encode(body + binascii.crc_hqx(body, 0).to_bytes(2, "big")) + b"\x00"


class CounterOffByOne(_Rewriting):
    """Answers SYNC n with counter n + 1."""

    def rewrite(self, m):
        if isinstance(m, Sample):
            return Sample(m.node, (m.counter + 1) & 0xFFFF, m.x, m.y, m.z, m.status)
        return m


class WrongByteOrder(_Rewriting):
    """Sends the SAMPLE counter big-endian (the spec: little-endian)."""

    def rewrite(self, m):
        if isinstance(m, Sample):
            c = m.counter
            return Sample(m.node, ((c & 0xFF) << 8) | (c >> 8), m.x, m.y, m.z, m.status)
        return m


class SyncAnsweredTwice(_Rewriting):
    """Answers every SYNC with two SAMPLEs."""

    def rewrite(self, m):
        return [m, m] if isinstance(m, Sample) else m


class SlowHeartbeat(ChipModel):
    """STATUS at twice the configured period."""

    def poll(self, now_s):
        hb = self.heartbeat_ms
        self.heartbeat_ms = hb * 2
        try:
            out = super().poll(now_s)
        finally:
            self.heartbeat_ms = hb
        return out


class NoReannounce(ChipModel):
    """Announces at boot but never again while unassigned."""

    def poll(self, now_s):
        if self.state == ChipState.BOOT:
            return []
        return super().poll(now_s)


class WrongNackReason(_Rewriting):
    """Every NACK carries the next reason code (BAD_STATE -> UNSUPPORTED, ...)."""

    def rewrite(self, m):
        if isinstance(m, Nack):
            return Nack(m.node, m.command, NackReason(int(m.reason) % 7 + 1))
        return m


class IgnoredReset(ChipModel):
    """ACKs RESET but keeps its state, node id and configuration."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Reset) and msg.node in (0, self.node):
            return [self._out(Ack(self.node, MsgType.RESET, 0))]
        return super().handle(frame, now_s, msg)


class AnswersBroadcast(ChipModel):
    """NACKs a broadcast the state table refuses (a NACK storm on a full sheet)."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        out = super().handle(frame, now_s, msg)
        if not out and isinstance(msg, Start) and msg.node == 0 and self.state == ChipState.BOOT:
            return [self._out(Nack(self.node, MsgType.START, NackReason.BAD_STATE))]
        return out


class IgnoresBroadcastStart(ChipModel):
    """Acts on START/STOP only when addressed to it, not when broadcast."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, (Start, Stop)) and msg.node == 0:
            return []
        return super().handle(frame, now_s, msg)


class NacksBroadcast(ChipModel):
    """NACKs a broadcast that does not decode (another version, an undefined type, a wrong length) as
    if it were addressed to it (the 1.0 reference did, for BAD_VERSION: a NACK storm)."""

    def _on_error(self, frame, err):
        out = super()._on_error(frame, err)
        hdr = frame_header(frame)
        if out or hdr is None or hdr[2] != 0 or err.reason.name in ("BAD_COBS", "SHORT", "BAD_CRC", "OVERSIZE"):
            return out
        from virtual_sheet.chip import _NACK_FOR
        return self._nack(hdr[1], _NACK_FOR[err.reason])


class NoPreviousId(ChipModel):
    """Forgets its previous provisional id: an ASSIGN that crossed its ANNOUNCE is lost (§3.3)."""

    def poll(self, now_s):
        out = super().poll(now_s)
        self.prev_node = None
        return out


class UptimeRestartsAtReset(ChipModel):
    """Restarts uptime_s at RESET (§4.4: it counts from power-on)."""

    def _boot(self, now_s):
        self.boot_s = now_s
        return super()._boot(now_s)


class MissedSyncsCountsWrap(ChipModel):
    """Counts the wrap 0xFFFF -> 0 and older counters as gaps (no serial-number arithmetic, §5.1)."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Sync) and self.streaming and self.last_counter is not None:
            gap = (msg.counter - self.last_counter - 1) & 0xFFFF
            if gap >= 0x7FFF:
                self.missed_syncs = min(255, self.missed_syncs + gap)
        return super().handle(frame, now_s, msg)


class ConfigWhileStreaming(ChipModel):
    """ACKs (and applies) CONFIG while STREAMING (§8.2: BAD_STATE)."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Config) and msg.node == self.node and self.state == ChipState.STREAMING:
            self.range = msg.range
            return [self._out(Ack(self.node, MsgType.CONFIG, 0))]
        return super().handle(frame, now_s, msg)


class NacksChipTypes(ChipModel):
    """NACKs UNKNOWN_COMMAND a chip -> host type addressed to it (the old §4.6 wording)."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if not isinstance(msg, DecodeError) and msg.DIRECTION == Direction.CHIP_TO_HOST and msg.node == self.node:
            return [self._out(Nack(self.node, msg.TYPE, NackReason.UNKNOWN_COMMAND))]
        return super().handle(frame, now_s, msg)


class AckDetailSet(_Rewriting):
    """Sends ACK with detail 1 (reserved: 0 in v1)."""

    def rewrite(self, m):
        return Ack(m.node, m.command, 1) if isinstance(m, Ack) else m


class ReservedCapabilityBit(_Rewriting):
    """Sets INFO capability bit 15 (reserved)."""

    def rewrite(self, m):
        if isinstance(m, Info):
            return Info(m.node, m.fw_major, m.fw_minor, m.fw_patch, m.protocol_version,
                        int(m.capabilities) | 0x8000, m.adc_bits, m.state)
        return m


class NoRxErrors(ChipModel):
    """Drops damaged frames without counting them in rx_errors."""

    def _on_error(self, frame, err):
        before = self.rx_errors
        out = super()._on_error(frame, err)
        self.rx_errors = before
        return out


class AssignIgnoresUid(ChipModel):
    """Takes an ASSIGN addressed to its node whatever its uid_low."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Assign) and msg.uid_low != (self.uid & 0xFFFFFFFF):
            msg = Assign(msg.node, msg.new_node, msg.link, self.uid & 0xFFFFFFFF)
        return super().handle(frame, now_s, msg)


class AssignedIdInBoot(ChipModel):
    """Speaks from node 0x0001 while unassigned (not a provisional id)."""

    def _boot_vars(self, now_s):
        super()._boot_vars(now_s)
        self._set_node(0x0001)

    def poll(self, now_s):
        out = super().poll(now_s)
        if self.state == ChipState.BOOT and out:
            self._set_node(0x0001)
            out = self._announce_info()
        return out


class CalReadNominal(_Rewriting):
    """Answers CAL_READ with the nominal calibration, whatever was written."""

    def rewrite(self, m):
        from protocol.messages import CalData
        if isinstance(m, CalData):
            return CalData(m.node, m.axis, 0, 0, 1024.0)
        return m


class AcceptsBadConfig(ChipModel):
    """ACKs a CONFIG with out-of-range fields (and ignores it)."""

    def _check(self, msg):
        from protocol.messages import Config
        if isinstance(msg, Config) and (msg.range > 3 or msg.filter > 3 or not 1 <= msg.rate_hz <= 4000):
            return None
        return super()._check(msg)

    def _apply(self, msg, rule, now_s):
        from protocol.messages import Config
        if isinstance(msg, Config) and (msg.range > 3 or msg.filter > 3 or not 1 <= msg.rate_hz <= 4000):
            return [self._out(Ack(self.node, MsgType.CONFIG, 0))]
        return super()._apply(msg, rule, now_s)


class ClaimsNoMultiRange(ChipModel):
    """Lacks MULTI_RANGE (INFO says so) but ACKs CONFIG range 1 instead of NACK UNSUPPORTED."""

    def __init__(self, uid, sensor, **kw):
        kw["capabilities"] = int(kw.get("capabilities", Capability.CAL_STORAGE) or 0) & ~Capability.MULTI_RANGE
        super().__init__(uid, sensor, **kw)

    def _check(self, msg):
        from protocol.messages import Config, NackReason as R
        reason = super()._check(msg)
        return None if (reason == R.UNSUPPORTED and isinstance(msg, Config)) else reason


class RefusesRepeatedConfig(ChipModel):
    """NACKs (BAD_STATE) a CONFIG identical to the configuration it already has."""

    def handle(self, frame, now_s, decoded=None):
        from protocol.messages import Config
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Config) and msg.node == self.node and self.configured and \
                (msg.rate_hz, msg.range, msg.filter, msg.heartbeat_ms) == \
                (self.rate_hz, self.range, self.filter, self.heartbeat_ms):
            return [self._out(Nack(self.node, MsgType.CONFIG, NackReason.BAD_STATE))]
        return super().handle(frame, now_s, msg)


class StartNotIdempotent(ChipModel):
    """NACKs START while already STREAMING."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Start) and msg.node == self.node and self.state == ChipState.STREAMING:
            return [self._out(Nack(self.node, MsgType.START, NackReason.BAD_STATE))]
        return super().handle(frame, now_s, msg)


class StreamsAfterStop(ChipModel):
    """ACKs STOP but keeps answering SYNC."""

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        if isinstance(msg, Stop) and msg.node == self.node and self.state == ChipState.STREAMING:
            return [self._out(Ack(self.node, MsgType.STOP, 0))]
        return super().handle(frame, now_s, msg)


class WrongPriority(ChipModel):
    """CAN: sends SAMPLE with priority 4 (the table: 2)."""

    def _sample(self, counter, now_s):
        f = super()._sample(counter, now_s)
        if isinstance(f, CanFrame):
            _p, t, v, n = split_id(f.arbitration_id)
            return CanFrame(make_id(t, n, priority=4, version=v), f.data, f.is_fd)
        return f


# ---------------------------------------------------------------------------------------------
# gateways (the gateway profile)
# ---------------------------------------------------------------------------------------------

class SilentGateway(Gateway):
    """Packs SNAPSHOTs but is no node (a 1.0 gateway): a host cannot learn that it packs (§13.1)."""

    def __init__(self, *a, **kw):
        kw["as_node"] = False
        super().__init__(*a, **kw)


class PassesHostSync(Gateway):
    """A SYNC source that passes the host's SYNC to its chips too: two sources on one segment (§13.3)."""

    def _from_host(self, frame, decoded, now_s):
        if type(decoded) is Sync and self.sync_source:
            self._dispatch(frame, decoded, now_s)
            return
        super()._from_host(frame, decoded, now_s)


class PacksOnlyAnswers(Gateway):
    """Packs only the links whose chip answered, leaving the others out instead of INVALID (§13.2)."""

    def _emit(self, frames, due_s):
        from protocol.framing import decode_frame, encode
        from protocol.messages import Snapshot
        out = []
        for f in frames:
            m = decode_frame(bytes(f).rstrip(b"\x00")) if isinstance(f, bytes) else None
            if isinstance(m, Snapshot):
                keep = [k for k in range(m.count) if not m.status[k] & 8]
                if keep:
                    out.append(encode(Snapshot.from_arrays(m.node, m.counter, m.first_link + keep[0],
                                                           m.counts[keep], m.status[keep])))
                continue
            out.append(f)
        super()._emit(out, due_s)


class _AcksChipCommands(GatewayNode):
    def handle(self, frame, decoded, now_s):
        out = super().handle(frame, decoded, now_s)
        if out and isinstance(decoded, (Config, Start, Stop)):
            return [self._out(Ack(self.node, decoded.TYPE, 0))]
        return out


class AcksChipCommands(Gateway):
    """ACKs CONFIG/START/STOP addressed to the gateway instead of NACK UNSUPPORTED (§13.1)."""

    node_class = _AcksChipCommands


class _NoStatus(GatewayNode):
    def poll(self, now_s):
        return [] if self.state == ChipState.IDLE else super().poll(now_s)


class GatewayWithoutStatus(Gateway):
    """Sends no STATUS once assigned (§13.1)."""

    node_class = _NoStatus


class PackingWithoutCapability(Gateway):
    """Says PACKING in GATEWAY_INFO without capability SNAPSHOT in INFO (§4.16)."""

    def _make_node(self):
        node = super()._make_node()
        node.capabilities &= ~Capability.SNAPSHOT
        return node


class _NacksBroadcastNode(GatewayNode):
    def handle(self, frame, decoded, now_s):
        out = super().handle(frame, decoded, now_s)
        hdr = frame_header(frame)
        if not out and hdr is not None and hdr[2] == 0 and getattr(decoded, "reason", None) is not None \
                and decoded.reason.name not in ("BAD_COBS", "SHORT", "BAD_CRC", "OVERSIZE"):
            return [self._out(Nack(self.node, hdr[1], NackReason.BAD_VERSION))]
        return out


class GatewayNacksBroadcast(Gateway):
    """NACKs a broadcast that does not decode (§4.6)."""

    node_class = _NacksBroadcastNode


class ImuGatewayLeavesChipsInFormat0(Gateway):
    """Says it packs 6-axis records (GATEWAY_INFO sample_format 1) but passes START on without configuring
    its chips (§16.5: it configures them itself): they answer SYNC with SAMPLEs it cannot pack."""

    def _configure_imu(self, start, now_s):
        return None


#: name -> (chip class, transport, allow_broadcast)
MUTANTS = {
    "dead_sensor": (DeadSensor, "serial", False),
    "frozen_sample": (FrozenSample, "serial", False),
    "wrong_crc": (WrongCrc, "serial", False),
    "wrong_crc_sample": (WrongCrcOnSamples, "serial", False),
    "counter_off_by_one": (CounterOffByOne, "serial", False),
    "wrong_byte_order": (WrongByteOrder, "serial", False),
    "sync_answered_twice": (SyncAnsweredTwice, "serial", False),
    "slow_heartbeat": (SlowHeartbeat, "serial", False),
    "no_reannounce": (NoReannounce, "serial", False),
    "no_previous_id": (NoPreviousId, "serial", False),
    "wrong_nack_reason": (WrongNackReason, "serial", False),
    "ignored_reset": (IgnoredReset, "serial", False),
    "answers_broadcast": (AnswersBroadcast, "serial", True),
    "nacks_broadcast": (NacksBroadcast, "serial", False),
    "ignores_broadcast_start": (IgnoresBroadcastStart, "serial", True),
    "nacks_chip_types": (NacksChipTypes, "serial", False),
    "ack_detail_set": (AckDetailSet, "serial", False),
    "reserved_capability_bit": (ReservedCapabilityBit, "serial", False),
    "no_rx_errors": (NoRxErrors, "serial", False),
    "assign_ignores_uid": (AssignIgnoresUid, "serial", False),
    "assigned_id_in_boot": (AssignedIdInBoot, "serial", False),
    "uptime_restarts_at_reset": (UptimeRestartsAtReset, "serial", False),
    "cal_read_nominal": (CalReadNominal, "serial", False),
    "accepts_bad_config": (AcceptsBadConfig, "serial", False),
    "claims_no_multi_range": (ClaimsNoMultiRange, "serial", False),
    "refuses_repeated_config": (RefusesRepeatedConfig, "serial", False),
    "start_not_idempotent": (StartNotIdempotent, "serial", False),
    "streams_after_stop": (StreamsAfterStop, "serial", False),
    "missed_syncs_counts_wrap": (MissedSyncsCountsWrap, "serial", False),
    "config_while_streaming": (ConfigWhileStreaming, "serial", False),
    "wrong_priority": (WrongPriority, "can", False),
}

#: the C firmware's mutants (capsheet_fw.h ``capsheet_mutant_t``) -> the Python mutant that breaks the
#: same rule (so the same checks must fail); `C_MUTANT_OPTIONS` the chip options a mutant needs
# ---- 6/9-axis chips (v1.2, docs/protocol.md §16): the Python model built with sensors= -------------

class ImuAnswersSample(_Rewriting):
    """Takes CONFIG_IMU but answers SYNC with the accelerometer's SAMPLE alone (§16.3)."""

    def rewrite(self, msg):
        if isinstance(msg, ImuSample):
            return Sample(msg.node, msg.counter, msg.x, msg.y, msg.z, msg.status)
        return msg


class ImuTimeWithoutCapability(ChipModel):
    """Reports no SAMPLE_TIME but sends a time_us (§16.1: −32768 without it)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.capabilities &= ~Capability.SAMPLE_TIME


class ImuAcceptsBadConfig(_Rewriting):
    """ACKs a CONFIG_IMU whose values are out of range (§16.2: BAD_VALUE); changes nothing."""

    def rewrite(self, msg):
        if isinstance(msg, Nack) and msg.command == MsgType.CONFIG_IMU and msg.reason == NackReason.BAD_VALUE:
            return Ack(msg.node, MsgType.CONFIG_IMU, 0)
        return msg


class ImuAccelFirst(ChipModel):
    """Classic CAN: sends a record's IMU_ACCEL before its IMU_GYRO (§16.4: GYRO, MAG, ACCEL)."""

    def handle(self, frame, now_s, decoded=None):
        out = super().handle(frame, now_s, decoded)
        imu = [f for f in out if isinstance(f, CanFrame) and split_id(f.arbitration_id)[1] in
               (MsgType.IMU_GYRO, MsgType.IMU_MAG, MsgType.IMU_ACCEL)]
        if len(imu) >= 2:
            return [imu[-1]] + imu[:-1] + [f for f in out if f not in imu]
        return out


class CalImuReadNominal(_Rewriting):
    """v1.3: answers CAL_IMU_READ with the nominal value, whatever was written (§17.2)."""

    def rewrite(self, msg):
        from protocol.messages import CalImuData, cal_block_nominal
        if isinstance(msg, CalImuData):
            return CalImuData(msg.node, msg.block, msg.index, 0, 0, cal_block_nominal(msg.block, msg.index))
        return msg


#: name -> (class, transport, sensors): the §16 mutants (checks 42-44), each a 6/9-axis chip, and §17's (45)
IMU_MUTANTS = {
    "imu_answers_sample": (ImuAnswersSample, "serial", "accel+gyro"),
    "imu_time_without_capability": (ImuTimeWithoutCapability, "serial", "accel+gyro+mag"),
    "imu_accepts_bad_config": (ImuAcceptsBadConfig, "serial", "accel+gyro"),
    "imu_accel_first": (ImuAccelFirst, "can", "accel+gyro"),
    "cal_imu_read_nominal": (CalImuReadNominal, "serial", "accel+gyro+mag"),
}


C_MUTANTS = {
    "dead_sensor": "dead_sensor", "frozen_sample": "frozen_sample", "wrong_crc": "wrong_crc",
    "wrong_crc_sample": "wrong_crc_sample", "counter_off_by_one": "counter_off_by_one",
    "sync_twice": "sync_answered_twice", "slow_heartbeat": "slow_heartbeat", "no_reannounce": "no_reannounce",
    "wrong_nack_reason": "wrong_nack_reason", "ignored_reset": "ignored_reset", "nacks_broadcast": "nacks_broadcast",
    "nacks_node_types": "nacks_chip_types", "ack_detail": "ack_detail_set", "no_rx_errors": "no_rx_errors",
    "assign_ignores_uid": "assign_ignores_uid", "no_previous_id": "no_previous_id",
    "uptime_reset": "uptime_restarts_at_reset", "cal_read_nominal": "cal_read_nominal",
    "accepts_bad_config": "accepts_bad_config", "ignores_capability": "claims_no_multi_range",
    "start_not_idempotent": "start_not_idempotent", "streams_after_stop": "streams_after_stop",
    "missed_syncs_wrap": "missed_syncs_counts_wrap", "config_while_streaming": "config_while_streaming",
    "reserved_capability_bit": "reserved_capability_bit", "refuses_repeated_config": "refuses_repeated_config",
    "answers_broadcast": "answers_broadcast", "ignores_broadcast_start": "ignores_broadcast_start",
    "wrong_priority": "wrong_priority", "cal_imu_read_nominal": "cal_imu_read_nominal",
    "imu_answers_sample": "imu_answers_sample", "imu_accel_first": "imu_accel_first",
    "imu_accepts_bad_config": "imu_accepts_bad_config",
}
#: ignores_capability ACKs a range the chip lacks: it must lack MULTI_RANGE, as its twin does
#: checks a C mutant's run adds to its twin's so that the broken frame is sent at all (a SAMPLE needs a SYNC)
C_MUTANT_EVIDENCE = {"wrong_priority": {24}}
C_MUTANT_OPTIONS = {"ignores_capability": dict(capabilities=int(Capability.CAL_STORAGE | Capability.FILTER))}

#: gateway mutants: name -> (gateway class, device options); the gateway profile must fail them
GATEWAY_MUTANTS = {
    "silent_gateway": (SilentGateway, dict(packed=True)),
    "passes_host_sync": (PassesHostSync, dict(packed=True, sync_rate_hz=50.0)),
    "packs_only_answers": (PacksOnlyAnswers, dict(packed=True)),
    "acks_chip_commands": (AcksChipCommands, dict(packed=True)),
    "gateway_without_status": (GatewayWithoutStatus, dict(packed=True)),
    "packing_without_capability": (PackingWithoutCapability, dict(packed=True)),
    "gateway_nacks_broadcast": (GatewayNacksBroadcast, dict(packed=True)),
    # a 6-axis sheet (the sheet's ``sensors``, taken out of the device options by the test)
    "imu_gateway_leaves_chips_in_format_0": (ImuGatewayLeavesChipsInFormat0, dict(packed=True, sensors="accel+gyro")),
}

class _SlottedSyncSource(Gateway):
    """A packing gateway that, as a SYNC source, passes the host's frames to its chips right after each
    SYNC it generates (a segment served in slots; §13.1 forwards every host frame and sets no latency)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self._held: list = []

    def _from_host(self, frame, decoded, now_s: float) -> None:
        if self.sync_rate_hz and type(decoded) is not Sync:
            self._held.append((frame, decoded))
        else:
            super()._from_host(frame, decoded, now_s)

    def poll(self, now_s: float) -> None:
        before = self.stats.syncs_generated
        super().poll(now_s)
        if self.stats.syncs_generated != before:
            held, self._held = self._held, []
            for frame, decoded in held:
                super()._from_host(frame, decoded, now_s)


class FlushesAt5ms(_SlottedSyncSource):
    """Healthy: a packing gateway that sends each SYNC's frames 5 ms after the SYNC, on a timer, even when
    every chip answered at once — §13.2 allows anywhere up to 10 ms (a chip behind it answered in time).
    As a SYNC source its STOP reaches the chip just after a SYNC the chip answers: that SYNC's SNAPSHOT
    follows the STOP's ACK."""

    flush_s = 0.005


class FlushesAt10ms(_SlottedSyncSource):
    """Healthy: the same at the last instant §13.2 allows, 10 ms after the SYNC (`SNAPSHOT_DEADLINE`). As a
    SYNC source at 145 Hz (6.9 ms) a SYNC's SNAPSHOT arrives after the next SYNC, and after the ACK of a
    second STOP sent at once: every time, not by chance."""

    flush_s = 0.010


#: healthy variants: name -> (sheet options, device options); the suite must pass every one. The gateways
#: cover what §13-§16 allow a gateway: each record format a chip may be reached by (SAMPLE, SNAPSHOT,
#: SNAPSHOT_IMU of format 1 and 2), SYNC source or not, packed frames anywhere in 0-10 ms after the SYNC
#: (at 145 Hz a 10 ms flush arrives after the next SYNC)
HEALTHY = {
    "noise_free": (dict(noise=0.0), dict()),
    "quiet_12_bit": (dict(noise=0.02), dict()),
    "packing_gateway": (dict(noise=0.02), dict(packed=True)),
    "several_chips_one_port": (dict(noise=0.5, lattice="3x3"), dict()),
    "sync_source_gateway": (dict(noise=0.02), dict(packed=True, sync_rate_hz=50.0)),
    "sync_source_gateway_flushing_at_5ms": (dict(noise=0.02), dict(packed=True, sync_rate_hz=50.0,
                                                                   gateway_class=FlushesAt5ms)),
    "packing_gateway_flushing_at_10ms": (dict(noise=0.02), dict(packed=True, gateway_class=FlushesAt10ms)),
    "imu6_chips_behind_a_format_1_packing_gateway": (dict(noise=0.02, sensors="accel+gyro"), dict(packed=True)),
    "imu9_chips_behind_a_sync_source_flushing_at_10ms": (
        dict(noise=0.02, sensors="accel+gyro+mag"), dict(packed=True, sync_rate_hz=145.0, gateway_class=FlushesAt10ms)),
}
