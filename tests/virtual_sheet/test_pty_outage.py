"""A virtual sheet's pty through an outage keeps its number: while the bus is away no other process
can take it (on a busy machine one did, and the host refused the sheet as another device), and the
bus comes back under it (virtual_sheet/pty.py)."""

from __future__ import annotations

import os
import time

import pytest
import serial

from virtual_sheet.devices import PtyDevice
from virtual_sheet.pty import PtyPort
from virtual_sheet.sheet import VirtualSheet

TIMEOUT_S = 5.0


def test_while_a_port_is_away_its_number_is_not_given_to_anyone_else(tmp_path):
    port = PtyPort("gw", tmp_path / "gw")
    port.open()
    tty = port.tty
    port.close()  # the outage: the master is gone
    others = []
    try:
        assert not os.path.exists(port.path)
        with pytest.raises(OSError):
            os.open(tty, os.O_RDWR | os.O_NOCTTY)  # nobody can open the slave whose master is gone
        # every other pty the machine hands out meanwhile has another number (the kernel gives the
        # lowest free one: were the port's free, the first ones would get it)
        others = [os.openpty() for _ in range(8)]
        assert tty not in {os.ttyname(s) for _, s in others}
        port.open()  # back: under its own number
        assert port.tty == tty and os.readlink(port.path) == tty
    finally:
        for fds in others:
            for fd in fds:
                os.close(fd)
        port.cleanup()
    # and once it is cleaned up for good, the number is free again
    m, s = os.openpty()
    os.close(m)
    os.close(s)


def test_a_sheet_back_from_an_outage_has_its_pty_number_while_others_ask_for_ptys_meanwhile():
    sheet = VirtualSheet("flat", "2x2", seed=1, faults="outage_at_s=0.3,outage_s=0.5")
    others = []
    with PtyDevice(sheet) as dev:
        first_tty = dev.tty
        host = serial.Serial(dev.path, timeout=0.05)
        deadline = time.monotonic() + TIMEOUT_S
        with pytest.raises(serial.SerialException):
            while time.monotonic() < deadline:
                host.read(1000)
        host.close()  # the host lets its side go, as it does when it sees the port lost
        try:
            while dev.down and len(others) < 16:  # other processes ask for ptys during the outage
                others.append(os.openpty())
                time.sleep(0.01)
            assert others and first_tty not in {os.ttyname(s) for _, s in others}
            deadline = time.monotonic() + TIMEOUT_S
            while not (dev.running and not dev.down and os.path.exists(dev.path)):
                assert time.monotonic() < deadline
                time.sleep(0.01)
            assert dev.tty == first_tty and os.readlink(dev.path) == first_tty
        finally:
            for fds in others:
                for fd in fds:
                    os.close(fd)
