"""Checks over everything the node sent during the run: framing, canonical encoding, the DBC (docs §2,
§4.5, §6, §7)."""

from __future__ import annotations

import math

from cobs import cobs

from protocol.can import decode_can
from protocol.framing import decode_frame, DecodeError, encode, HEADER
from protocol.messages import Ack, Announce, GatewayInfo, Info, Message, MsgType, Nack, Sample, Status

from ..session import CheckFailed, PortLost, require, Session, Skip

from .registry import check, PROFILES


# ---------------------------------------------------------------------------------------------
# Everything the node sent during the run
# ---------------------------------------------------------------------------------------------

@check("6.2, 6.1, 6.3, 7.1, 7.2, 4.8", "every frame from the node decoded (COBS, CRC / identifier, priority, "
       "lengths); no SNAPSHOT from a chip",
       "a host drops the node's frames (wrong CRC variant, framing, identifier layout or priority)",
       "CRC-16/CCITT-FALSE (check 0x29B1) over header + payload, MSB first, then COBS and 0x00; on CAN "
       "the §4 priority in bits 28..26 and classic frames for payloads ≤ 8 bytes", profiles=PROFILES,
       needs_node=False)
def c_framing(s: Session):
    """Runs also when no node was found: frames that arrive damaged, all of them, are a node's framing."""
    p = s.port
    if p.frames == 0 and p.damaged == 0:
        raise Skip("nothing received")
    if s.cur is None and not p.damaged:
        raise Skip("no node found, and nothing damaged arrived")
    chip = s.systematic_damage()
    if chip:
        raise CheckFailed(chip)
    if p.damaged and not p.lossy:
        raise CheckFailed(f"{p.damaged} of {p.damaged + p.frames} frames did not decode "
                          f"({dict(p.damage)}): the node's framing, not the port")
    bad = p.bad_ids  # the port's FrameAudit: §7.1 identifiers of every CAN frame received
    require(not bad, "; ".join(bad[:3]))
    if s.profile == "chip":
        require(not s.by_type.get((int(MsgType.SNAPSHOT), True)), "a chip sent SNAPSHOT (§4.8: gateways only)")
    if p.damaged:
        raise PortLost(f"{p.damaged} of {p.damaged + p.frames} frames did not decode ({dict(p.damage)})")
    mine = sum(v for (t, ok), v in s.by_type.items() if ok)
    return f"{mine} frames from the node, {p.frames} in all"


def _from(s: Session, raw: bytes) -> bool:
    """The serial frame came from a node id the node under test used (header intact)."""
    try:
        body = cobs.decode(raw.rstrip(b"\x00"))
    except cobs.DecodeError:
        return False
    return len(body) >= 4 and HEADER.unpack_from(body)[2] in s.my_nodes


def _canonical_serial(raw: bytes) -> str | None:
    msg = decode_frame(raw.rstrip(b"\x00"))
    if isinstance(msg, DecodeError):
        return None
    ref = encode(msg)
    return None if ref == raw else f"{msg.TYPE.name}: sent {raw.hex(' ')}, reference {ref.hex(' ')}"


@check("2, 4.5, 4.2, 4.4", "every frame is byte-identical to the reference encoding of its fields "
       "(reserved bits 0, little-endian)",
       "the node sends non-zero reserved bits or a non-canonical encoding; a future version may give them meaning",
       "send reserved bits and bytes as 0 (ACK detail, flags, capabilities); encode as the golden vectors (§9)",
       profiles=PROFILES)
def c_canonical(s: Session):
    s.need_chip()
    bad, n = [], 0
    if s.port.kind == "serial":
        for raw in list(s.port.raw):
            if not _from(s, raw):
                continue
            if isinstance(decode_frame(raw.rstrip(b"\x00")), DecodeError):
                continue
            n += 1
            d = _canonical_serial(raw)
            if d:
                bad.append(d)
    else:  # CAN: the port's FrameAudit keeps every extended data frame received
        from protocol.can import to_can
        for aid, data, fd in list(s.port.raw):
            msg = decode_can(aid, data, is_fd=fd)
            if isinstance(msg, DecodeError) or not isinstance(msg, Message) or msg.node not in s.my_nodes:
                continue
            n += 1
            ref = to_can(msg, fd=fd)
            if ref.data != data or (ref.arbitration_id & 0x03FFFFFF) != (aid & 0x03FFFFFF):
                bad.append(f"{msg.TYPE.name}: sent {aid:08X}#{data.hex()}, reference "
                           f"{ref.arbitration_id:08X}#{ref.data.hex()}")
    if n == 0:
        raise Skip("no frame of the node was recorded: nothing to compare")
    require(not bad, f"{len(bad)} of {n} frames differ from the reference encoding; first: {bad[0] if bad else ''}")
    acks = [m for m in s.acks if m.detail != 0]
    require(not acks, f"{len(acks)} ACK with detail != 0 (reserved in 1.1), first: {acks[:1]}")
    return f"{n} frames compared"


@check("7.3", "every frame from the node decodes with the DBC (cantools) to the same fields",
       "CAN tools using protocol/capsheet.dbc misread the node",
       "use the §7.1 identifiers and §4 layouts (the DBC is generated from them)", transport="can",
       profiles=PROFILES)
def c_dbc(s: Session):
    s.need_chip()
    from protocol.dbc import load_database
    db = load_database()
    bad, n = [], 0
    for aid, data, fd in list(s.port.raw):  # CAN: (arbitration_id, data, is_fd) of every frame received
        msg = decode_can(aid, data, is_fd=fd)
        if not isinstance(msg, (Sample, Ack, Nack, Status, Announce, Info, GatewayInfo)) or msg.node not in s.my_nodes:
            continue
        n += 1
        try:
            sig = db.get_message_by_frame_id(aid).decode(data, decode_choices=False)
        except Exception as exc:  # noqa: BLE001 - cantools raises several kinds
            bad.append(f"{aid:08X}#{data.hex()}: {exc}")
            continue
        diff = {k: (v, getattr(msg, k)) for k, v in sig.items()
                if hasattr(msg, k) and not math.isclose(float(v), float(getattr(msg, k)), rel_tol=1e-6)}
        if diff:
            bad.append(f"{msg.TYPE.name} {aid:08X}#{data.hex()}: DBC vs decoder {diff}")
    if n == 0:
        raise Skip("no frame of the node was recorded: nothing to decode")
    require(not bad, f"{len(bad)} of {n} frames: {bad[0] if bad else ''}")
    return f"{n} frames decoded by the DBC"
