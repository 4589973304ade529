"""`host.conformance.session.Session.fresh_boot` when the RESET goes to an id the chip has left.

A chip in BOOT takes its next provisional id every 1 s (§3.2) and re-announces from there. On a
slow host the RESET can reach the old id after the move: nothing answers it but the re-announce.
The suite then failed a conforming chip ("RESET not answered ACK, ANNOUNCE, INFO", seen on the C
firmware's 6/9-axis runs beside two busy cores); it now finds the chip, once, and sends the RESET
again. Real pty, the virtual sheet's chips; the old id is made stale by hand, so the case is
exact rather than a race."""

from __future__ import annotations

from host.conformance import Port
from host.conformance.session import Session
from host.transport.ports import SerialTransport
from protocol.messages import Ack, Info, MsgType
from virtual_sheet.devices import PtyDevice
from virtual_sheet.sheet import VirtualSheet


def test_a_reset_to_an_id_the_boot_chip_has_left_is_sent_again_where_it_is():
    sheet = VirtualSheet("flat", "2x2", seed=3)
    uid = sheet.uids[0]
    with PtyDevice(sheet) as dev:
        t = SerialTransport(str(dev.path), reconnect=False)
        port = Port(t)
        try:
            s = Session(port, timeout_s=0.5, uid=uid)  # answer window 1.5 s: a re-announce (1 s) falls in it
            s.relocate()
            assert s.cur is not None
            s.info = next(m for m in s.request_info(s.cur) if isinstance(m, Info))
            s.fresh_boot()  # the chip in BOOT, re-announcing every second
            moved_from = s.cur
            s.cur = 0x8001 if moved_from != 0x8001 else 0x8002  # an id it does not speak from
            acks_before = len(s.acks)
            s.fresh_boot()  # raised "RESET not answered ACK, ANNOUNCE, INFO" before
            assert s.cur not in (0x8001, 0x8002)
            resets = [a for a in s.acks[acks_before:] if isinstance(a, Ack) and a.command == MsgType.RESET]
            assert len(resets) == 1  # the RESET sent again reached it, once
        finally:
            port.close()
            t.close()
