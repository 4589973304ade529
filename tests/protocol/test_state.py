"""`protocol.state`: the chip's and the gateway's state tables (docs/protocol.md §8, §13.4) read
rule by rule, and the periodic deadline of §14 on a simulated clock."""

import pytest

from protocol.messages import ChipState, MsgType
from protocol.state import Reply, gateway_rule_for, next_deadline, rule_for

B, I, S, F = ChipState.BOOT, ChipState.IDLE, ChipState.STREAMING, ChipState.FAULT


def test_a_chip_streams_from_start_to_stop():
    assert rule_for(B, MsgType.ASSIGN).next_state == I
    assert rule_for(I, MsgType.START).next_state == S
    assert rule_for(S, MsgType.SYNC).reply == Reply.SAMPLE
    assert rule_for(I, MsgType.SYNC).reply == Reply.NONE  # assigned, not started: silent
    assert rule_for(S, MsgType.STOP).next_state == I


@pytest.mark.parametrize("state", list(ChipState))
def test_reset_boots_and_get_info_answers_in_every_state(state):
    assert rule_for(state, MsgType.RESET).reply == Reply.ACK_THEN_BOOT
    assert rule_for(state, MsgType.RESET).next_state == B
    assert rule_for(state, MsgType.GET_INFO).reply == Reply.ANNOUNCE_INFO


def test_what_a_state_does_not_take_has_no_rule():
    # no rule: NACK BAD_STATE when addressed, ignored when broadcast
    assert rule_for(B, MsgType.START) is None
    assert rule_for(B, MsgType.CONFIG) is None
    assert rule_for(S, MsgType.CONFIG) is None  # no reconfiguring while streaming
    assert rule_for(B, MsgType.CAL_READ) is None


def test_a_fault_keeps_its_state_and_validated_commands_say_so():
    assert rule_for(F, MsgType.START).next_state is None and rule_for(F, MsgType.SYNC).reply == Reply.SAMPLE
    assert rule_for(I, MsgType.CONFIG).validate and rule_for(I, MsgType.CAL_WRITE).validate
    assert not rule_for(I, MsgType.START).validate


def test_a_gateway_answers_chip_commands_unsupported_and_has_no_sync_rule():
    assert gateway_rule_for(B, MsgType.ASSIGN).next_state == I
    for t in (MsgType.CONFIG, MsgType.START, MsgType.STOP, MsgType.CAL_WRITE, MsgType.CAL_READ):
        assert gateway_rule_for(I, t).reply == Reply.UNSUPPORTED
    assert gateway_rule_for(I, MsgType.SYNC) is None
    assert gateway_rule_for(S, MsgType.GET_INFO) is None  # a gateway has two states only


def test_a_periodic_send_keeps_its_phase_and_skips_what_it_missed():
    # period 1 s due at 1.0: sent on time, late by 0.3 s (phase kept), then 2.5 s late (skipped)
    sends, due = [], 1.0
    for now in (1.0, 2.3, 5.5, 6.5):
        if now >= due:
            sends.append(now)
            due = next_deadline(due, 1.0, now)
    assert sends == [1.0, 2.3, 5.5, 6.5]
    assert next_deadline(1.0, 1.0, 1.0) == 2.0
    assert next_deadline(2.0, 1.0, 2.3) == 3.0  # no drift from the late send
    assert next_deadline(3.0, 1.0, 5.5) == 6.5  # a whole period behind: from now, never twice
