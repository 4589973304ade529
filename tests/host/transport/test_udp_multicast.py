"""`host.transport.udp_multicast.IsolatedUdpMulticastBus`: python-can's udp_multicast bus that hears only its
own group. Real sockets on loopback; the two-sheets-side-by-side CLI test is in
tests/host/cli/test_host.py."""

from __future__ import annotations

import sys
import time

import pytest

from tests.host.udp_lock import udp_multicast_lock

can = pytest.importorskip("can")

pytestmark = [pytest.mark.xdist_group("udp_multicast"),
              pytest.mark.skipif(not sys.platform.startswith("linux"), reason="IP_MULTICAST_ALL is Linux's")]

A, B = "239.74.163.50", "239.74.163.51"


def _bus(interface, group):
    try:
        return can.Bus(interface=interface, channel=group)
    except can.CanError as exc:  # no multicast route on this machine
        pytest.skip(f"udp_multicast not available here: {exc}")


def _received(bus, wait_s=1.0) -> list[int]:
    """Arbitration ids of every frame ``bus`` receives until it has been quiet for ``wait_s``."""
    ids = []
    while (m := bus.recv(wait_s)) is not None:
        ids.append(m.arbitration_id)
    return ids


def test_a_bus_hears_its_own_group_and_not_another():
    with udp_multicast_lock():
        plain = _bus("udp_multicast", A)  # python-can's own: the Linux behaviour being fixed
        iso = _bus("capsheet_udp_multicast", A)
        tx_a, tx_b = _bus("udp_multicast", A), _bus("udp_multicast", B)
        try:
            assert iso.stale_datagrams == 0  # nothing was on either group before
            tx_b.send(can.Message(arbitration_id=0x0B, data=b"b"))
            tx_a.send(can.Message(arbitration_id=0x0A, data=b"a"))
            tx_b.send(can.Message(arbitration_id=0x0C, data=b"c"))
            assert _received(iso) == [0x0A]
            # the control: python-can's bus on the same group hears the other group too (if this
            # kernel did not, the isolation above would be untested)
            assert sorted(_received(plain, 0.2)) == [0x0A, 0x0B, 0x0C]
        finally:
            for b in (plain, iso, tx_a, tx_b):
                b.shutdown()


def test_it_talks_to_python_cans_plain_bus_both_ways():
    """Same wire format, port and group: a plain ``udp_multicast`` program on the group is heard,
    and hears it."""
    with udp_multicast_lock():
        iso, plain = _bus("capsheet_udp_multicast", A), _bus("udp_multicast", A)
        try:
            iso.send(can.Message(arbitration_id=0x123456, data=bytes(range(8)), is_extended_id=True))
            m = plain.recv(2.0)
            assert m is not None and m.arbitration_id == 0x123456 and bytes(m.data) == bytes(range(8))
            plain.send(can.Message(arbitration_id=0x42, data=b"\x01\x02", is_extended_id=False))
            # loopback hands a sender its own frames back (the host's EchoFilter drops them)
            got = []
            while (m := iso.recv(1.0)) is not None:
                got.append((m.arbitration_id, bytes(m.data)))
            assert got == [(0x123456, bytes(range(8))), (0x42, b"\x01\x02")]
        finally:
            iso.shutdown()
            plain.shutdown()


def test_datagrams_queued_before_the_filter_are_discarded_and_counted():
    """`isolate` on a socket that already holds datagrams (joined, filter not yet off) drains them."""
    import socket
    from host.transport.udp_multicast import isolate
    with udp_multicast_lock():
        plain = _bus("udp_multicast", A)
        tx = _bus("udp_multicast", B)
        try:
            for i in range(3):
                tx.send(can.Message(arbitration_id=i, data=b""))
            time.sleep(0.2)  # let loopback deliver (an upper bound on nothing: only waits)
            assert isolate(plain.fileno()) == 3
            tx.send(can.Message(arbitration_id=9, data=b""))
            assert _received(plain, 0.3) == []  # now filtered: the other group is not heard
            s = socket.socket(fileno=plain.fileno())
            try:
                assert s.getsockopt(socket.IPPROTO_IP, 49) == 0  # IP_MULTICAST_ALL off
            finally:
                s.detach()
        finally:
            plain.shutdown()
            tx.shutdown()


@pytest.mark.parametrize("group", ["not-an-ip", "1.2.3.4"])
def test_a_group_that_cannot_be_opened_is_one_error_and_no_shutdown_warning(group):
    """python-can's bus raises from its constructor after its base class counted it open; the
    half-made bus must not log "was not properly shut down" under the user's one-line error."""
    import subprocess
    code = ("import gc, logging, can\n"
            "logging.basicConfig(level=logging.WARNING)\n"
            "try:\n"
            f"    can.Bus(interface='capsheet_udp_multicast', channel={group!r})\n"
            "except (can.CanError, OSError) as exc:\n"
            "    print('refused:', type(exc).__name__)\n"
            "gc.collect()\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("refused:"), r.stdout + r.stderr
    assert "not properly shut down" not in r.stderr, r.stderr


def test_a_burst_sent_while_the_bus_is_not_read_is_all_received():
    """A host or sheet a busy machine did not schedule for a while: 3,000 frames (a 24-chip sheet's
    0.9 s at 145 Hz) arrive while nobody reads. The bus asks for a receive buffer that queues them
    all (`RCVBUF_BYTES`), where the default one drops what does not fit, without a trace; python-can's
    plain bus beside it is the control (on this kernel it loses part of the burst, or the test shows
    nothing)."""
    from host.transport.udp_multicast import RCVBUF_BYTES
    n = 3000
    limit = int(open("/proc/sys/net/core/rmem_max").read())
    if limit < RCVBUF_BYTES:
        pytest.skip(f"net.core.rmem_max is {limit} bytes here: the kernel grants no more")
    with udp_multicast_lock():
        iso, plain, tx = _bus("capsheet_udp_multicast", A), _bus("udp_multicast", A), _bus("udp_multicast", A)
        try:
            for k in range(n):
                tx.send(can.Message(arbitration_id=k, data=b"\x00" * 8, is_extended_id=True))
            got = _received(iso, 0.5)
            assert got == list(range(n)), (len(got), n)  # every frame, in order
            assert len(_received(plain, 0.2)) < n  # the default buffer: the control
        finally:
            for b in (iso, plain, tx):
                b.shutdown()
