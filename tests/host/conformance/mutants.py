"""Deliberately broken chips ("mutants") on the Python chip model: each breaks one rule of
docs/protocol.md, so the conformance suite must fail it — and only in the checks that hold a chip
to that rule (tests/host/conformance/test_mutants.py). Each subclasses `ChipModel` (whose behaviour
is not changed) and rewrites what it hears or sends. The C firmware has its own mutant builds,
by compile-time switch, in firmware_ref/ports/qemu-mps2/main.c (``make -C firmware_ref qemu MUTANT=``).
"""

from __future__ import annotations

import binascii

from cobs import cobs

from protocol.can import CanFrame, decode_can, make_id, split_id, to_can
from protocol.framing import DecodeError, decode_frame, encode
from protocol.messages import (Ack, Announce, Assign, Capability, ChipState, Direction, Info, MsgType, Nack,
                               NackReason, Reset, Sample, Start, Stop)
from virtual_sheet.chip import ChipModel

__all__ = ["MUTANTS"]


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


class StaleMarkedFresh(ChipModel):
    """Converts once, then repeats that value at every SYNC without the STALE flag."""

    def __init__(self, uid, sensor, **kw):
        frozen = {}

        def once(now_s):
            if "v" not in frozen:
                frozen["v"] = sensor(now_s)
            return frozen["v"]
        super().__init__(uid, once, **kw)


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


#: name -> (chip class, transport, allow_broadcast)
MUTANTS = {
    "dead_sensor": (DeadSensor, "serial", False),
    "stale_marked_fresh": (StaleMarkedFresh, "serial", False),
    "wrong_crc": (WrongCrc, "serial", False),
    "counter_off_by_one": (CounterOffByOne, "serial", False),
    "wrong_byte_order": (WrongByteOrder, "serial", False),
    "sync_answered_twice": (SyncAnsweredTwice, "serial", False),
    "slow_heartbeat": (SlowHeartbeat, "serial", False),
    "no_reannounce": (NoReannounce, "serial", False),
    "wrong_nack_reason": (WrongNackReason, "serial", False),
    "ignored_reset": (IgnoredReset, "serial", False),
    "answers_broadcast": (AnswersBroadcast, "serial", True),
    "ignores_broadcast_start": (IgnoresBroadcastStart, "serial", True),
    "nacks_chip_types": (NacksChipTypes, "serial", False),
    "ack_detail_set": (AckDetailSet, "serial", False),
    "reserved_capability_bit": (ReservedCapabilityBit, "serial", False),
    "no_rx_errors": (NoRxErrors, "serial", False),
    "assign_ignores_uid": (AssignIgnoresUid, "serial", False),
    "assigned_id_in_boot": (AssignedIdInBoot, "serial", False),
    "cal_read_nominal": (CalReadNominal, "serial", False),
    "accepts_bad_config": (AcceptsBadConfig, "serial", False),
    "claims_no_multi_range": (ClaimsNoMultiRange, "serial", False),
    "refuses_repeated_config": (RefusesRepeatedConfig, "serial", False),
    "start_not_idempotent": (StartNotIdempotent, "serial", False),
    "streams_after_stop": (StreamsAfterStop, "serial", False),
    "wrong_priority": (WrongPriority, "can", False),
}
