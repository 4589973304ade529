"""The chip state machine (docs/protocol.md §8). Everything that decides what a chip does with a
command lives in these tables, h11-style: the Python chip model, the C firmware and the
conformance suite are all checked against them.

A chip reacts to a decoded host -> chip frame addressed to it (``node`` == its node id) or
broadcast (``node`` == 0). `RULES` maps ``(state, type)`` to a `Rule`; a pair not in the table is
refused with NACK BAD_STATE when addressed to the chip and ignored when broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from .messages import ChipState, MsgType

__all__ = ["Reply", "Rule", "RULES", "rule_for", "ANNOUNCE_PERIOD_S", "SYNC_REPLY_DEADLINE_S"]

ANNOUNCE_PERIOD_S = 1.0  #: an unassigned chip repeats ANNOUNCE + INFO this often (docs §3.2)
SYNC_REPLY_DEADLINE_S = 0.002  #: a chip's SAMPLE leaves within this of SYNC's end on its bus (docs §5.1)


class Reply(Enum):
    """What the chip sends back."""

    NONE = "none"  #: nothing
    ACK = "ack"  #: ACK(command=type)
    SAMPLE = "sample"  #: SAMPLE(counter of the SYNC)
    ANNOUNCE_INFO = "announce_info"  #: ANNOUNCE then INFO
    CAL_DATA = "cal_data"  #: CAL_DATA of the asked axis
    ACK_THEN_BOOT = "ack_then_boot"  #: ACK from the current node, then boot: ANNOUNCE + INFO


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
RULES[_B, MsgType.ASSIGN] = Rule(Reply.ACK, _I, validate=True)
RULES[_I, MsgType.ASSIGN] = Rule(Reply.ACK, _I, validate=True)
RULES[_F, MsgType.ASSIGN] = Rule(Reply.ACK, _F, validate=True)
RULES[_I, MsgType.CONFIG] = Rule(Reply.ACK, validate=True)
RULES[_F, MsgType.CONFIG] = Rule(Reply.ACK, validate=True)
RULES[_I, MsgType.START] = Rule(Reply.ACK, _S)
RULES[_S, MsgType.START] = Rule(Reply.ACK)
RULES[_F, MsgType.START] = Rule(Reply.ACK)  # stays FAULT: answers SYNC with INVALID samples
RULES[_I, MsgType.STOP] = Rule(Reply.ACK)
RULES[_S, MsgType.STOP] = Rule(Reply.ACK, _I)
RULES[_F, MsgType.STOP] = Rule(Reply.ACK)
RULES[_S, MsgType.SYNC] = Rule(Reply.SAMPLE)
RULES[_F, MsgType.SYNC] = Rule(Reply.SAMPLE)  # with SampleStatus.INVALID, once START was received
RULES[_B, MsgType.SYNC] = Rule(Reply.NONE)
RULES[_I, MsgType.SYNC] = Rule(Reply.NONE)
RULES[_I, MsgType.CAL_WRITE] = Rule(Reply.ACK, validate=True)
for _st in _ASSIGNED:
    RULES[_st, MsgType.CAL_READ] = Rule(Reply.CAL_DATA)


def rule_for(state: ChipState, msg_type: MsgType) -> Rule | None:
    """The rule, or None: NACK BAD_STATE if addressed, ignore if broadcast."""
    return RULES.get((state, msg_type))
