"""Checks in IDLE: configuration, NACKs, calibration, heartbeat, damaged input (docs §4.4-§4.15, §6.3,
§6.4, §7, §8.1-§8.5, §12)."""

from __future__ import annotations

import statistics

from cobs import cobs

from host.transport.ports import CanTransport
from protocol.crc import crc16_ccitt_false
from protocol.framing import encode_frame, HEADER
from protocol.messages import (Ack, Announce, CalData, CalRead, CalWrite, Capability, ChipState, Config,
                               MsgType, Nack, NackReason, PROTOCOL_VERSION, Status, StatusFlag)
from protocol.state import TIMER_TOLERANCE

from ..session import acked, HEARTBEAT_MS, require, Session, Skip

from .discovery import theil_sen_period
from .registry import check, PROFILES


# ---------------------------------------------------------------------------------------------
# IDLE: configuration, NACKs, calibration, heartbeat
# ---------------------------------------------------------------------------------------------

@check("4.11, 8.3", "CONFIG (valid) is acknowledged, also the same one again",
       "the chip cannot be configured", "ACK a CONFIG whose fields are in range, in IDLE and FAULT")
def c_config(s: Session):
    s.ensure_idle()
    for _ in range(2):  # the same CONFIG again is ACKed too
        ans = s.request(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=HEARTBEAT_MS))
        require(acked(ans, s.node, MsgType.CONFIG), f"answered {ans}")


@check("8.4, 4.4", f"STATUS every heartbeat_ms ({HEARTBEAT_MS} ms ± 5 % + slack/2); an accepted CONFIG restarts "
       "the period; IDLE, CONFIGURED",
       "the host's liveness monitoring misjudges the chip (its clock or scheduler is off)",
       "send STATUS every heartbeat_ms from a free-running time base (a hardware counter, not a count of "
       "timer interrupts); at an accepted CONFIG start the period again; set CONFIGURED after CONFIG")
def c_heartbeat(s: Session):
    """The period by Theil-Sen over 9 heartbeats; the restart by a CONFIG sent half a period after a
    STATUS: a chip that restarts sends the next STATUS a whole period after the CONFIG, one that does
    not half a period after it. Lateness (the host's, the port's) only makes that gap longer, so the
    bound is one-sided: the suite passes a conforming chip on a loaded machine."""
    s.ensure_idle()
    gaps = []
    for _ in range(3):
        st = s.statuses(1)
        require(bool(st), f"no STATUS within {max(1.5, 3 * s.timeout_s):.1f} s")
        s.port.sleep(HEARTBEAT_MS / 2000)
        s.drain()
        s.port.send(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=HEARTBEAT_MS))
        def after_ack(ms):
            k = next((i for i, m in enumerate(ms) if acked([m], s.node, MsgType.CONFIG)), None)
            return k is not None and any(isinstance(m, Status) for m in ms[k + 1:])
        got = s.collect(s.answer_s, after_ack)
        k = next((i for i, (_, m) in enumerate(got) if acked([m], s.node, MsgType.CONFIG)), None)
        sts = [t for t, m in got[k + 1:] if isinstance(m, Status)] if k is not None else []
        require(k is not None and bool(sts), f"CONFIG: ACK then STATUS expected; got {[m for _, m in got]}")
        gaps.append((sts[0] - got[k][0]) * 1000)  # a STATUS of the old period before the ACK is no evidence
    gap = statistics.median(gaps)
    n = 9
    st = s.statuses(n, timeout_s=n * HEARTBEAT_MS / 1000 * 1.5 + s.timeout_s)
    require(len(st) >= 3, f"{len(st)} STATUS in {n * HEARTBEAT_MS * 1.5 / 1000 + s.timeout_s:.2f} s at "
                          f"heartbeat_ms={HEARTBEAT_MS}")
    # Theil-Sen: the median of the slopes between every pair of heartbeats, so one heartbeat held up
    # by the host (or the port) does not move the estimate; a chip's own clock error does
    period = theil_sen_period([t for t, _ in st]) * 1000
    tol = TIMER_TOLERANCE * HEARTBEAT_MS + s.slack_ms / 2
    require(abs(period - HEARTBEAT_MS) <= tol, f"period {period:.1f} ms over {len(st)} heartbeats "
                                               f"({HEARTBEAT_MS} ± {tol:.1f} ms)")
    low = (1 - TIMER_TOLERANCE) * HEARTBEAT_MS - s.slack_ms
    require(gap >= low, f"a CONFIG half a period after a STATUS: the next STATUS came {gap:.1f} ms after its ACK "
                        f"(median of {', '.join(f'{g:.1f}' for g in gaps)}; at least {low:.0f} ms): CONFIG did not "
                        f"restart the period")
    m = st[-1][1]
    require(m.state == ChipState.IDLE, f"state {ChipState(m.state).name}")
    require(bool(m.flags & StatusFlag.CONFIGURED), f"flags {StatusFlag(m.flags)!r}")
    require(m.flags & ~0x0F == 0, f"reserved STATUS flag bits set: 0x{m.flags:02X}")
    up = [x.uptime_s for _, x in st]
    require(up == sorted(up), f"uptime_s goes backwards: {up}")
    return f"period {period:.1f} ms over {len(st)} heartbeats; after a CONFIG the next STATUS {gap:.1f} ms later"


@check("4.11, 4.6", "CONFIG with a field out of range: NACK BAD_VALUE",
       "the chip accepts a configuration it cannot honour",
       "validate CONFIG before applying it: range > 3, filter > 3, rate_hz 0 or > 4000 -> NACK 3 BAD_VALUE")
def c_config_bad_value(s: Session):
    s.ensure_idle()
    for cfg in (Config(s.node, range=7), Config(s.node, rate_hz=0), Config(s.node, rate_hz=4001),
                Config(s.node, filter=4)):
        ans = s.request(cfg)
        require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_VALUE)], f"{cfg} answered {ans}")


@check("4.11, 4.2", "a capability the chip lacks: NACK UNSUPPORTED (CONFIG range, filter; CAL_WRITE store)",
       "the chip claims to do what it cannot, or refuses what it advertises",
       "range != 0 without MULTI_RANGE, filter != 0 without FILTER and CAL_WRITE flags bit 0 without "
       "CAL_STORAGE -> NACK 5 UNSUPPORTED; with the capability, ACK")
def c_unsupported(s: Session):
    s.ensure_idle()
    caps = int(s.info.capabilities)
    for cfg, cap in ((Config(s.node, range=1, heartbeat_ms=HEARTBEAT_MS), Capability.MULTI_RANGE),
                     (Config(s.node, filter=2, heartbeat_ms=HEARTBEAT_MS), Capability.FILTER)):
        ans = s.request(cfg)
        s.request(Config(s.node, range=0, heartbeat_ms=HEARTBEAT_MS))  # back to ±2 g whatever happened
        ok = acked(ans, s.node, MsgType.CONFIG) if caps & cap else \
            ans == [Nack(s.node, MsgType.CONFIG, NackReason.UNSUPPORTED)]
        require(ok, f"{cfg} ({'with' if caps & cap else 'without'} {cap.name}) answered {ans}")
    if not caps & Capability.CAL_STORAGE:
        ans = s.request(CalWrite(s.node, axis=0, flags=1, offset_q4=0, sensitivity=1024.0))
        require(ans == [Nack(s.node, MsgType.CAL_WRITE, NackReason.UNSUPPORTED)],
                f"CAL_WRITE store without CAL_STORAGE answered {ans}")
    return f"capabilities {Capability(caps)!r}"


#: the first host -> node type code the spec leaves undefined (the table of §4, from the code)
_FIRST_UNDEFINED = max(int(t) for t in MsgType if t >= 0x10) + 1


@check("8.1, 4", "an undefined type outside 0x01..0x0F addressed to the node: NACK UNKNOWN_COMMAND",
       "a host cannot tell a node that lacks a command from a lost frame",
       f"NACK reason 1 UNKNOWN_COMMAND, command = the type code, for an undefined type 0x00 or "
       f"0x{_FIRST_UNDEFINED:02X}..0x3F addressed to the node", profiles=PROFILES)
def c_unknown(s: Session):
    s.ensure_node()
    ans = s.raw(0x3F, s.node, b"")
    require(ans == [Nack(s.node, 0x3F, NackReason.UNKNOWN_COMMAND)], f"answered {ans}")


@check("8.1, 4", "a node -> host type addressed to the chip is ignored (no NACK), defined or not",
       "on a shared bus the chip answers other nodes' frames (a NACK storm)",
       "drop every frame whose type is in 0x01..0x0F silently, whatever its node and version, and do not count it")
def c_chip_type_ignored(s: Session):
    s.ensure_idle()
    for t, payload in ((MsgType.STATUS, bytes(8)), (0x0A, b""), (MsgType.GATEWAY_INFO, bytes(8))):
        ans = s.silent(lambda: s.port.send_raw(t, s.node, payload))
        require(ans == [], f"a type 0x{t:02X} frame addressed to the chip was answered {ans}")


@check("8.1, 4.6", "a payload of the wrong length: NACK BAD_LENGTH",
       "the chip acts on truncated or padded commands",
       "compare the payload length with §4's size for the type; on a mismatch NACK 2 BAD_LENGTH")
def c_bad_length(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.START, s.node, b"\x01")
    require(ans == [Nack(s.node, MsgType.START, NackReason.BAD_LENGTH)], f"answered {ans}")


@check("12, 8.1", "a frame of another protocol version addressed to the node: NACK BAD_VERSION, in version 1",
       "a host of another version cannot learn that the node speaks v1",
       "do not decode a frame whose version is not 1; NACK 6 BAD_VERSION in the node's own version",
       profiles=PROFILES)
def c_bad_version(s: Session):
    s.ensure_node()
    ans = s.raw(MsgType.GET_INFO, s.node, b"", version=PROTOCOL_VERSION + 1)
    require(ans == [Nack(s.node, MsgType.GET_INFO, NackReason.BAD_VERSION)], f"answered {ans}")


@check("8.1, 4.9, 4.15", "a field the decoder rejects (CAL_READ axis 3, a SYNC addressed to the chip): NACK BAD_VALUE",
       "the chip reads or writes out of bounds on a bad field",
       "range-check every field on decode; NACK 3 BAD_VALUE")
def c_bad_field(s: Session):
    s.ensure_idle()
    ans = s.raw(MsgType.CAL_READ, s.node, b"\x03")
    require(ans == [Nack(s.node, MsgType.CAL_READ, NackReason.BAD_VALUE)], f"CAL_READ axis 3 answered {ans}")
    ans = s.raw(MsgType.SYNC, s.node, b"\x01\x00")
    require(ans == [Nack(s.node, MsgType.SYNC, NackReason.BAD_VALUE)], f"a SYNC addressed to the chip answered {ans}")


@check("4.6, 8.1", "a broadcast is never NACKed: another version, an undefined type, a wrong length (GET_INFO)",
       "one broadcast draws a NACK from every chip of the sheet at once (a storm)",
       "answer nothing to a broadcast (node 0) that does not decode; NACK only frames addressed to you",
       profiles=PROFILES)
def c_broadcast_never_nacked(s: Session):
    s.ensure_node()
    for what, t, payload, v in (("GET_INFO of version 2", MsgType.GET_INFO, b"", PROTOCOL_VERSION + 1),
                                ("undefined type 0x3F", 0x3F, b"", None),
                                ("GET_INFO with a 1-byte payload", MsgType.GET_INFO, b"\x01", None)):
        ans = s.silent(lambda: s.port.send_raw(t, 0, payload, version=v))
        require(not [m for m in ans if isinstance(m, Nack)], f"a broadcast {what} was answered {ans}")
        require(not [m for m in ans if isinstance(m, (Ack, Announce))], f"a broadcast {what} was acted on: {ans}")


@check("4.15, 4.7", "CAL_WRITE then CAL_READ gives the calibration back (CAL_DATA)",
       "calibration written by the host is lost or corrupted",
       "keep the CAL_WRITE fields per axis and answer CAL_READ with CAL_DATA carrying them")
def c_calibration(s: Session):
    s.ensure_idle()
    for axis, off, sens in ((1, -21, 1003.5), (2, 37, 998.25)):
        ans = s.request(CalWrite(s.node, axis=axis, flags=0, offset_q4=off, sensitivity=sens))
        require(acked(ans, s.node, MsgType.CAL_WRITE), f"CAL_WRITE answered {ans}")
        ans = s.request(CalRead(s.node, axis=axis))
        require(ans == [CalData(s.node, axis=axis, flags=0, offset_q4=off, sensitivity=sens)],
                f"CAL_READ axis {axis} answered {ans}")


@check("8.5, 6.4, 6.3, 4.4", "damaged serial input is dropped silently, counted in rx_errors (not another "
       "node's frames), and the chip recovers",
       "line noise makes the chip act, hang, or go unreported",
       "drop every run that fails COBS/CRC/length without answering; count each in rx_errors (saturating), "
       "not frames for other nodes; resynchronise at the next 0x00", transport="serial")
def c_bad_input_serial(s: Session):
    s.ensure_idle()
    before = s.status().rx_errors
    body = HEADER.pack(PROTOCOL_VERSION, MsgType.GET_INFO, s.node)
    bad_crc = cobs.encode(body + ((crc16_ccitt_false(body) ^ 0x0100).to_bytes(2, "big"))) + b"\x00"
    junk = [b"\x05\x01\x02\x03\x00", bad_crc, b"\x01" * 1100 + b"\x00", b"\x03\x01\x02\x00"]
    other = s.node - 1 if s.node > 1 else s.node + 1
    foreign = encode_frame(MsgType.START, other, b"\x01")  # another node's wrong length: not counted (§8.5)
    ans = s.silent(lambda: [s.port.send_bytes(j) for j in junk + [foreign]])
    require(ans == [], f"answered damaged input with {ans}")
    ans = s.request_info(s.node)  # answered only once every byte before it was processed
    require(len(ans) == 2, f"no answer to GET_INFO after the damage: {ans}")
    after = s.status().rx_errors  # a heartbeat sent after that answer
    require(after - before == len(junk) or after == 255,
            f"rx_errors {before} -> {after}, expected +{len(junk)} (4 damaged runs; not the frame for node {other})")
    return f"rx_errors {before} -> {after}"


@check("7.1, 7.2", "frames that are not capsheet frames are not answered, and the chip recovers",
       "foreign traffic on the bus makes the chip act",
       "accept only 29-bit identifiers of version 1; ignore standard frames", transport="can")
def c_bad_input_can(s: Session):
    s.ensure_idle()
    if not isinstance(s.port.transport, CanTransport):
        raise Skip("standard-identifier frames need a CAN transport")
    ans = s.silent(lambda: s.port.transport.send_frame(0x123, b"\x01\x02", extended=False))
    require(ans == [], f"answered a standard-identifier frame with {ans}")
    ans = s.request_info(s.node)
    require(len(ans) == 2, f"no answer to GET_INFO afterwards: {ans}")
