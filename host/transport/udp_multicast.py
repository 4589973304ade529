"""python-can's ``udp_multicast`` bus, isolated to its own group: `IsolatedUdpMulticastBus`.

python-can's `can.interfaces.udp_multicast.UdpMulticastBus` binds every bus to one UDP port (43113)
on every address and joins its group. On Linux a socket bound to a wildcard address receives the
datagrams of *every* group any socket on the machine joined for that port, unless the socket's
``IP_MULTICAST_ALL`` option is off (``ip(7)``; ``IPV6_MULTICAST_ALL`` for IPv6, ``ipv6(7)``): two
sheets on ``239.74.163.2`` and ``239.74.163.3`` on one machine would hear each other's chips.
(BSD and macOS filter by the socket's own memberships already.)

`IsolatedUdpMulticastBus` is python-can's bus, unchanged on the wire (msgpack frames, the same port
and groups: it talks to plain ``udp_multicast`` buses of other programs), with that option turned
off. It reaches the socket through python-can's public ``fileno()``: a duplicate of the descriptor
shares the socket, so the option set on it holds for the bus's own. Datagrams the kernel queued in
the microseconds between python-can joining the group and the option being set may be another
group's; they are read and discarded once, at open (counted in `stale_datagrams`), as if the bus
had opened those microseconds later.

Every datagram is one frame (a chip's SAMPLE), and what the kernel cannot queue for a reader that
was not scheduled is dropped without a trace: the default receive buffer (``net.core.rmem_default``,
212,992 bytes) held 256 small datagrams here, 74 ms of a 24-chip sheet at 145 Hz. The bus asks for
`RCVBUF_BYTES` (``SO_RCVBUF``, ``socket(7)``; the kernel grants up to ``net.core.rmem_max``), so a
host or sheet left unscheduled for a while on a busy machine reads its frames late instead of
losing them. Registered as python-can interface ``capsheet_udp_multicast``
(the ``can.interface`` entry point in pyproject.toml), so

    bus = can.Bus(interface="capsheet_udp_multicast", channel="239.74.163.3")

opens it in any program; `host.transport.ports.CanTransport` (``--can udp_multicast:GROUP``) and
``capsheet virtual --can-interface udp_multicast`` open it for ``udp_multicast``.
"""

from __future__ import annotations

import os
import socket
import sys

import can
from can.interfaces.udp_multicast import UdpMulticastBus

#: <linux/in.h> and <linux/in6.h>; Python's socket module does not name them
IP_MULTICAST_ALL = 49
IPV6_MULTICAST_ALL = 29

#: the receive buffer a bus asks for (module docstring); the kernel grants at most ``net.core.rmem_max``
RCVBUF_BYTES = 4 << 20

#: python-can's interface name for this bus (entry point ``can.interface``)
INTERFACE = "capsheet_udp_multicast"


def isolate(fd: int) -> int:
    """Ask for a receive buffer of `RCVBUF_BYTES` on the UDP socket ``fd``; on Linux turn
    ``IP_MULTICAST_ALL`` (or ``IPV6_MULTICAST_ALL``) off, then read and discard the datagrams
    already queued; returns how many (0 off Linux)."""
    sock = socket.socket(fileno=os.dup(fd))  # family and type read from the descriptor
    try:
        if sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) < RCVBUF_BYTES:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        if not sys.platform.startswith("linux"):
            return 0
        if sock.family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL, 0)
        else:
            sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
        stale = 0
        while True:
            try:
                sock.recv(65536, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                return stale
            stale += 1
    finally:
        sock.close()


class IsolatedUdpMulticastBus(UdpMulticastBus):
    """python-can's `UdpMulticastBus` that hears its own group only (module docstring).

    Same parameters as `UdpMulticastBus` (``channel`` the group, ``port``, ``hop_limit``, ``fd``).
    """

    def __init__(self, channel: str = UdpMulticastBus.DEFAULT_GROUP_IPv6, *args, **kwargs) -> None:
        try:
            super().__init__(channel, *args, **kwargs)
        except BaseException:
            # python-can's bus failed to open (a group that is no address, no multicast route):
            # mark the half-made bus shut down, or its __del__ logs "was not properly shut down"
            # under the user's one-line error
            can.BusABC.shutdown(self)
            raise
        try:
            #: datagrams queued before the group filter was set, discarded at open
            self.stale_datagrams = isolate(self.fileno())
        except OSError as exc:
            self.shutdown()
            raise can.CanInitializationError(
                f"cannot isolate udp_multicast group {channel!r}: {exc}") from exc
