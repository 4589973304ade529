"""The gateway as a node on the wire (docs/protocol.md §13.1, §13.4), sans-I/O: its announce rounds,
ASSIGN, GET_INFO and RESET, its STATUS heartbeat, and the NACKs it sends for chip commands. The
`virtual_sheet.gateway.Gateway` consults it for every host frame and keeps its flags and runs current."""

from __future__ import annotations

from protocol.can import to_can
from protocol.framing import DecodeError, ErrorReason, encode
from protocol.messages import (NODE_BROADCAST, PROTOCOL_VERSION, Ack, Announce, Assign, Capability, ChipState,
                               Direction, GatewayFlag, GatewayInfo, Info, Message, MsgType, Nack, NackReason,
                               SampleFormat, Status, is_node_to_host_type, provisional_node)
from protocol.state import ANNOUNCE_PERIOD_S, GATEWAY_HEARTBEAT_MS, Reply, gateway_rule_for, next_deadline

__all__ = ["GatewayNode", "gateway_uid", "FIRMWARE_VERSION"]

FIRMWARE_VERSION = (0, 1, 0)  #: the virtual gateway's INFO fw_major, fw_minor, fw_patch
_INTEGRITY = (ErrorReason.BAD_COBS, ErrorReason.SHORT, ErrorReason.BAD_CRC, ErrorReason.OVERSIZE)
_NACK_FOR = {ErrorReason.BAD_VERSION: NackReason.BAD_VERSION, ErrorReason.UNKNOWN_TYPE: NackReason.UNKNOWN_COMMAND,
             ErrorReason.BAD_LENGTH: NackReason.BAD_LENGTH, ErrorReason.BAD_FIELD: NackReason.BAD_VALUE}


def gateway_uid(sheet_seed: int, stream: int) -> int:
    """The uid of a virtual sheet's gateway ``stream``: fixed by the sheet's seed, in a range of its
    own (prefix 0x6A7E) so it never meets a chip's."""
    return (0x6A7E << 48) | ((int(sheet_seed) & 0xFFFFFFFF) << 16) | (int(stream) & 0xFFFF)


class GatewayNode:
    """A gateway as a node on the wire (docs/protocol.md §13), sans-I/O: the frames it sends, and
    what it does with the host frames addressed to it. The `Gateway` consults it for every host
    frame and forwards the frame to its chips as well (§13.1: a chip in BOOT may share its id).

    ``flags`` and ``runs`` are read when GATEWAY_INFO is sent: the `Gateway` keeps them current.
    """

    def __init__(self, uid: int, *, can: bool, fd: bool, capabilities: int) -> None:
        self.uid = uid
        self.can = can
        self.capabilities = Capability(int(capabilities) | Capability.GATEWAY | (Capability.CAN_FD if fd else 0))
        self.flags = GatewayFlag.NONE
        self.sample_format = int(SampleFormat.ACCEL_12)  #: what GATEWAY_INFO says its SNAPSHOT words are
        self.runs: list[tuple[int, int]] = []
        self.sync_rate_hz = 0
        self.refused_syncs = 0  #: host SYNCs not passed on (saturating at 255 in STATUS)
        self.rx_errors = 0
        self.boot_s = 0.0
        self.powered = False
        self._boot_vars(0.0)

    def _boot_vars(self, now_s: float) -> None:
        self.state = ChipState.BOOT
        self.salt = 0
        self.node = provisional_node(self.uid, 0)
        self.prev_node: int | None = None
        self.next_announce_s = now_s + ANNOUNCE_PERIOD_S
        self.next_heartbeat_s: float | None = None
        self.rx_errors = 0
        self.refused_syncs = 0

    def _out(self, msg: Message):
        return to_can(msg) if self.can else encode(msg)

    def announce(self) -> list:
        """ANNOUNCE, INFO, one GATEWAY_INFO per run (§13.1)."""
        out = [self._out(Announce(self.node, self.uid)),
               self._out(Info(self.node, *FIRMWARE_VERSION, PROTOCOL_VERSION, int(self.capabilities), 0, self.state))]
        for first, count in (self.runs or [(0, 0)]):
            out.append(self._out(GatewayInfo(self.node, int(self.flags), self.sample_format, first, count,
                                             min(0xFFFF, int(round(self.sync_rate_hz))))))
        return out

    def power_on(self, now_s: float) -> list:
        self.powered = True
        self.boot_s = now_s
        self._boot_vars(now_s)
        return self.announce()

    def poll(self, now_s: float) -> list:
        if not self.powered:
            return []
        if self.state == ChipState.BOOT:
            if now_s < self.next_announce_s:
                return []
            self.salt += 1
            self.prev_node = self.node
            self.node = provisional_node(self.uid, self.salt)
            self.next_announce_s = next_deadline(self.next_announce_s, ANNOUNCE_PERIOD_S, now_s)
            return self.announce()
        if self.next_heartbeat_s is not None and now_s >= self.next_heartbeat_s:
            self.next_heartbeat_s = next_deadline(self.next_heartbeat_s, GATEWAY_HEARTBEAT_MS / 1000, now_s)
            return [self._out(Status(self.node, self.state, 0, min(255, self.rx_errors), min(255, self.refused_syncs),
                                     int(max(0.0, now_s - self.boot_s)) & 0xFFFFFFFF))]
        return []

    def refuse_sync(self) -> None:
        self.refused_syncs += 1

    def handle(self, frame, decoded, now_s: float) -> list:
        """A host frame (already decoded by the `Gateway`): the gateway's own answer (§13.4)."""
        if not self.powered:
            return []
        if isinstance(decoded, DecodeError):
            if decoded.reason in _INTEGRITY:
                self.rx_errors += 1
                return []
            hdr = _header(frame)
            if hdr is None:
                return []
            _v, t, node = hdr
            if node != self.node or is_node_to_host_type(t):
                return []  # broadcast or another node's: never a NACK (§8.1)
            return [self._out(Nack(self.node, t & 0xFF, _NACK_FOR[decoded.reason]))]
        node = decoded.node
        t = decoded.TYPE
        if decoded.DIRECTION != Direction.HOST_TO_CHIP or t == MsgType.SYNC:
            return []
        addressed = node == self.node or (t == MsgType.ASSIGN and self.state == ChipState.BOOT
                                          and node == self.prev_node and node is not None)
        if not addressed and not (node == NODE_BROADCAST and t in (MsgType.GET_INFO, MsgType.RESET)):
            return []
        if t == MsgType.ASSIGN and decoded.uid_low != (self.uid & 0xFFFFFFFF):
            return []
        rule = gateway_rule_for(self.state, t)
        if rule is None or rule.reply is Reply.UNSUPPORTED:
            return [self._out(Nack(self.node, t, NackReason.UNSUPPORTED))] if addressed else []
        if rule.reply is Reply.ANNOUNCE_INFO:
            return self.announce()
        if rule.reply is Reply.ACK_THEN_BOOT:
            ack = self._out(Ack(self.node, t, 0))
            self._boot_vars(now_s)
            return [ack] + self.announce()
        assert isinstance(decoded, Assign)
        if self.state == ChipState.BOOT:
            self.next_heartbeat_s = now_s + GATEWAY_HEARTBEAT_MS / 1000
        self.node = decoded.new_node
        self.prev_node = None
        self.state = ChipState.IDLE
        return [self._out(Ack(self.node, t, 0))]


def _header(frame):
    """``(version, type, node)`` of an intact frame (the chip model's `frame_header`)."""
    from .chip import frame_header
    return frame_header(frame)
