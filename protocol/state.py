"""The state machines of a chip and of a gateway (docs/protocol.md §8, §13) and the protocol's
timing (§14). Everything that decides what a node does with a command lives in these tables,
h11-style: the Python chip model, the chip array, the C firmware, the virtual gateway and the
conformance suite are all checked against them.

A chip reacts to a decoded host -> node frame addressed to it (``node`` == its node id) or
broadcast (``node`` == 0). `RULES` maps ``(state, type)`` to a `Rule`; a pair not in the table is
refused with NACK BAD_STATE when addressed to the chip and ignored when broadcast. `chip_table`
renders the whole table — every state by every input, the inputs that never reach `RULES`
(damage, other versions, node -> host types, undefined types) included — as docs/protocol.md §8.2
prints it (a test keeps the two identical).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from .messages import ChipState, MsgType

__all__ = ["Reply", "Rule", "RULES", "rule_for", "GATEWAY_RULES", "gateway_rule_for", "chip_table",
           "gateway_table", "ANNOUNCE_PERIOD_S", "SYNC_REPLY_DEADLINE_S", "DEFAULT_HEARTBEAT_MS",
           "TIMER_TOLERANCE", "GATEWAY_HEARTBEAT_MS", "SNAPSHOT_DEADLINE_S", "DEFAULT_RATE_HZ", "next_deadline"]

# ---- timing (docs §14) ----------------------------------------------------------------------
ANNOUNCE_PERIOD_S = 1.0  #: an unassigned node repeats ANNOUNCE + INFO this often (§3.2)
SYNC_REPLY_DEADLINE_S = 0.002  #: a chip's SAMPLE SHOULD leave within this of SYNC's end on its bus (§5.1)
DEFAULT_HEARTBEAT_MS = 1000  #: a chip's STATUS period from ASSIGN until a CONFIG sets another (§8.4)
DEFAULT_RATE_HZ = 145  #: a chip's rate_hz until a CONFIG sets another (§4.11)
TIMER_TOLERANCE = 0.05  #: every period of §14 is kept within ±5 % (the node's clock)
GATEWAY_HEARTBEAT_MS = 1000  #: an assigned gateway's STATUS period (§13.1)
SNAPSHOT_DEADLINE_S = 0.010  #: a packing gateway sends a counter's SNAPSHOT by SYNC + this (§13.2)


def next_deadline(previous: float, period: float, now: float) -> float:
    """The deadline after a periodic send that was due at ``previous`` and went out at ``now`` (§14):
    ``previous + period`` — no drift — unless that is not after ``now`` (the node fell a whole period
    behind): then ``now + period``, so it skips what it missed and never sends twice back to back.

    >>> next_deadline(1.0, 1.0, 1.2), next_deadline(1.0, 1.0, 2.5)
    (2.0, 3.5)
    """
    n = previous + period
    return n if n > now else now + period


class Reply(Enum):
    """What the node sends back."""

    NONE = "none"  #: nothing
    ACK = "ack"  #: ACK(command=type)
    SAMPLE = "sample"  #: SAMPLE(counter of the SYNC)
    ANNOUNCE_INFO = "announce_info"  #: ANNOUNCE then INFO (a gateway: then GATEWAY_INFO)
    CAL_DATA = "cal_data"  #: CAL_DATA of the asked axis
    CAL_IMU_DATA = "cal_imu_data"  #: CAL_IMU_DATA of the asked element (new in 1.3, §17)
    ACK_THEN_BOOT = "ack_then_boot"  #: ACK from the current node, then boot: ANNOUNCE + INFO
    UNSUPPORTED = "unsupported"  #: NACK UNSUPPORTED when addressed (a gateway's answer to chip commands)


@dataclass(frozen=True, slots=True)
class Rule:
    reply: Reply
    next_state: ChipState | None = None  #: None: stay
    validate: bool = False  #: fields are checked first; a bad value is NACK BAD_VALUE / UNSUPPORTED


_B, _I, _S, _F = ChipState.BOOT, ChipState.IDLE, ChipState.STREAMING, ChipState.FAULT
_ASSIGNED = (_I, _S, _F)

RULES: dict[tuple[ChipState, MsgType], Rule] = {}
for _st in ChipState:
    RULES[_st, MsgType.GET_INFO] = Rule(Reply.ANNOUNCE_INFO)
    RULES[_st, MsgType.RESET] = Rule(Reply.ACK_THEN_BOOT, _B)
RULES[_B, MsgType.ASSIGN] = Rule(Reply.ACK, _I)
RULES[_I, MsgType.ASSIGN] = Rule(Reply.ACK, _I)
RULES[_F, MsgType.ASSIGN] = Rule(Reply.ACK, _F)
RULES[_I, MsgType.CONFIG] = Rule(Reply.ACK, validate=True)
RULES[_F, MsgType.CONFIG] = Rule(Reply.ACK, validate=True)
RULES[_I, MsgType.CONFIG_IMU] = Rule(Reply.ACK, validate=True)  # new in 1.2, §16.2: as CONFIG
RULES[_F, MsgType.CONFIG_IMU] = Rule(Reply.ACK, validate=True)
RULES[_I, MsgType.START] = Rule(Reply.ACK, _S)
RULES[_S, MsgType.START] = Rule(Reply.ACK)
RULES[_F, MsgType.START] = Rule(Reply.ACK)  # stays FAULT: answers SYNC with INVALID samples
RULES[_I, MsgType.STOP] = Rule(Reply.ACK)
RULES[_S, MsgType.STOP] = Rule(Reply.ACK, _I)
RULES[_F, MsgType.STOP] = Rule(Reply.ACK)  # stays FAULT: stops answering SYNC
RULES[_S, MsgType.SYNC] = Rule(Reply.SAMPLE)
RULES[_F, MsgType.SYNC] = Rule(Reply.SAMPLE)  # with SampleStatus.INVALID, once START was received
RULES[_B, MsgType.SYNC] = Rule(Reply.NONE)
RULES[_I, MsgType.SYNC] = Rule(Reply.NONE)
RULES[_I, MsgType.CAL_WRITE] = Rule(Reply.ACK, validate=True)
for _st in _ASSIGNED:
    RULES[_st, MsgType.CAL_READ] = Rule(Reply.CAL_DATA)
# new in 1.3, §17.2: as CAL_WRITE / CAL_READ; both check the block's sensor (UNSUPPORTED without it)
RULES[_I, MsgType.CAL_IMU_WRITE] = Rule(Reply.ACK, validate=True)
for _st in _ASSIGNED:
    RULES[_st, MsgType.CAL_IMU_READ] = Rule(Reply.CAL_IMU_DATA, validate=True)


def rule_for(state: ChipState, msg_type: MsgType) -> Rule | None:
    """The rule, or None: NACK BAD_STATE if addressed, ignore if broadcast."""
    return RULES.get((state, msg_type))


# ---- the gateway (docs §13.4): two states, BOOT (unassigned) and IDLE (assigned) ------------------
GATEWAY_RULES: dict[tuple[ChipState, MsgType], Rule] = {}
for _st in (_B, _I):
    GATEWAY_RULES[_st, MsgType.GET_INFO] = Rule(Reply.ANNOUNCE_INFO)
    GATEWAY_RULES[_st, MsgType.RESET] = Rule(Reply.ACK_THEN_BOOT, _B)
    GATEWAY_RULES[_st, MsgType.ASSIGN] = Rule(Reply.ACK, _I)
    for _t in (MsgType.CONFIG, MsgType.START, MsgType.STOP, MsgType.CAL_WRITE, MsgType.CAL_READ, MsgType.CONFIG_IMU,
               MsgType.CAL_IMU_WRITE, MsgType.CAL_IMU_READ):
        GATEWAY_RULES[_st, _t] = Rule(Reply.UNSUPPORTED)


def gateway_rule_for(state: ChipState, msg_type: MsgType) -> Rule | None:
    """A gateway's rule for a frame addressed to it (SYNC is §13.3's business, never here)."""
    return GATEWAY_RULES.get((state, msg_type))


# ---- the tables as docs/protocol.md prints them ----------------------------------------------------

_CELL = {Reply.NONE: "—", Reply.ACK: "ACK", Reply.SAMPLE: "SAMPLE", Reply.ANNOUNCE_INFO: "ANNOUNCE, INFO",
         Reply.CAL_DATA: "CAL_DATA", Reply.CAL_IMU_DATA: "CAL_IMU_DATA", Reply.ACK_THEN_BOOT: "ACK, ANNOUNCE, INFO", Reply.UNSUPPORTED: "NACK 5"}


def _cell(rule: Rule | None, state: ChipState, t: MsgType) -> str:
    if rule is None:
        return "NACK 4"
    text = _CELL[rule.reply]
    if t == MsgType.SYNC and state == _F:
        text = "SAMPLE INVALID if started, else —"
    if rule.validate:
        text = "check fields; " + text
    if rule.next_state is not None and rule.next_state != state:
        text += f" → {rule.next_state.name}"
    return text


def chip_table() -> str:
    """The chip's complete state table (docs §8.2) as markdown: every input by every state."""
    states = list(ChipState)
    rows = ["| input (addressed to the chip) | " + " | ".join(s.name for s in states) + " |",
            "|---|" + "---|" * len(states)]

    def row(name: str, cells: list[str]) -> None:
        rows.append(f"| {name} | " + " | ".join(cells) + " |")

    for t in (MsgType.SYNC, MsgType.ASSIGN, MsgType.CONFIG, MsgType.START, MsgType.STOP, MsgType.GET_INFO,
              MsgType.RESET, MsgType.CAL_WRITE, MsgType.CAL_READ, MsgType.CONFIG_IMU, MsgType.CAL_IMU_WRITE,
              MsgType.CAL_IMU_READ):
        name = t.name + (" (broadcast only)" if t == MsgType.SYNC else
                         " (uid_low matches)" if t == MsgType.ASSIGN else "")
        row(name, [_cell(rule_for(s, t), s, t) for s in states])
    row("ASSIGN, uid_low differs", ["—"] * len(states))
    row("a node → host type 0x01..0x0F, defined or not", ["—"] * len(states))
    row("an undefined type 0x00, 0x1C..0x3F", ["NACK 1"] * len(states))
    row("another protocol version", ["NACK 6"] * len(states))
    row("a defined host → node type of the wrong length", ["NACK 2"] * len(states))
    row("a field out of range (decoder: BAD_FIELD)", ["NACK 3"] * len(states))
    row("damaged (serial OVERSIZE, BAD_COBS, SHORT, BAD_CRC)", ["—, counted"] * len(states))
    return "\n".join(rows) + "\n"


def gateway_table() -> str:
    """The gateway's table (docs §13.4) as markdown: frames addressed to the gateway's node id."""
    rows = ["| input (addressed to the gateway) | BOOT | IDLE |", "|---|---|---|"]
    for t in (MsgType.ASSIGN, MsgType.GET_INFO, MsgType.RESET, MsgType.CONFIG, MsgType.START, MsgType.STOP,
              MsgType.CAL_WRITE, MsgType.CAL_READ, MsgType.CONFIG_IMU, MsgType.CAL_IMU_WRITE, MsgType.CAL_IMU_READ):
        name = t.name + (" (uid_low matches)" if t == MsgType.ASSIGN else "")
        cells = []
        for s in (_B, _I):
            rule = gateway_rule_for(s, t)
            text = _CELL[rule.reply]
            if t == MsgType.GET_INFO:
                text = "ANNOUNCE, INFO, GATEWAY_INFO"
            elif t == MsgType.RESET:
                text = "ACK, ANNOUNCE, INFO, GATEWAY_INFO"
            if rule.next_state is not None and rule.next_state != s:
                text += f" → {rule.next_state.name}"
            cells.append(text)
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"
