"""One session per port and reconnects only to the same device (host/transport/portlock.py), on real
ptys: the lock another process holds, named by its pid and command line; a port held refused
before it is opened; another pty put under the same path refused on reconnect, never written to
and never switched to raw mode; the same pty number back accepted."""

from __future__ import annotations

import os
import subprocess
import sys
import termios
import time

import pytest

from host.transport.portlock import DeviceIdentity, different, holders, identify, in_use_message, parse_proc_locks
from host.transport.ports import CanTransport, PortInUseError, SerialTransport
from protocol import SampleBatch, encode
from protocol.messages import Sample
from virtual_sheet.devices import open_pty

#: a process that opens a port as a capsheet session does (pyserial, exclusive) and waits
HOLDER = ("import serial, sys, time; p = serial.serial_for_url(sys.argv[1], exclusive=True); "
          "print('held', flush=True); time.sleep(60)")


def _hold(path: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLDER, path], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "held"
    return p


@pytest.fixture
def pty_pair():
    m, s = os.openpty()
    yield m, s, os.ttyname(s)
    for fd in (m, s):
        try:
            os.close(fd)
        except OSError:
            pass


def test_proc_locks_lines_name_the_holder_of_that_file_only():
    text = ("1: FLOCK  ADVISORY  WRITE 4242 00:1a:3 0 EOF\n"
            "1: -> FLOCK  ADVISORY  WRITE 4243 00:1a:3 0 EOF\n"  # waiting, not holding
            "2: FLOCK  ADVISORY  WRITE 77 00:1a:30 0 EOF\n"      # another inode
            "3: POSIX  ADVISORY  WRITE 78 00:1b:3 0 EOF\n")      # another file system
    assert parse_proc_locks(text, os.makedev(0, 0x1A), 3) == [4242]
    assert parse_proc_locks("", os.makedev(0, 0x1A), 3) == []


def test_a_port_another_process_holds_is_refused_naming_it(pty_pair, tmp_path):
    _m, _s, name = pty_pair
    link = tmp_path / "sheet"
    os.symlink(name, link)
    p = _hold(name)
    try:
        assert [pid for pid, _ in holders(str(link))] == [p.pid]
        with pytest.raises(PortInUseError) as err:
            SerialTransport(str(link))
        msg = str(err.value)
        assert "\n" not in msg and f"process {p.pid}" in msg and "serial_for_url" in msg and name in msg, msg
        with pytest.raises(PortInUseError):  # an SLCAN adapter on that tty: the same lock
            CanTransport(f"slcan:{link}", sleep_after_open=0)
    finally:
        p.kill()
        p.wait()
    t = SerialTransport(str(link))  # free again once the holder is gone, however it ended
    try:
        # ... and now this session holds it: a second one (pyserial's own lock) cannot take it
        out = subprocess.run([sys.executable, "-c", HOLDER, name], timeout=30, capture_output=True, text=True)
        assert out.returncode != 0 and "Could not exclusively lock" in out.stderr, out.stderr
    finally:
        t.close()


def test_the_in_use_line_without_a_holder_still_says_in_use(pty_pair):
    msg = in_use_message(pty_pair[2], [])
    assert "is in use by another session" in msg and "\n" not in msg


def test_identity_and_what_differs(pty_pair):
    _m, s, name = pty_pair
    a = identify(name)
    assert a == identify(name, s) and a.rdev == os.stat(name).st_rdev and a.usb is None
    b = DeviceIdentity(os.makedev(os.major(a.rdev), os.minor(a.rdev) + 1))
    assert different(a, b) == f"device {os.major(a.rdev)}:{os.minor(a.rdev) + 1}, not {os.major(a.rdev)}:{os.minor(a.rdev)}"
    usb = DeviceIdentity(a.rdev, (0x0403, 0x6001, "A1"))
    assert different(usb, DeviceIdentity(a.rdev, (0x0403, 0x6001, "A1"))) is None
    assert different(usb, DeviceIdentity(a.rdev, (0x1A86, 0x7523, None))) == "USB 1a86:7523, not 0403:6001"
    assert different(usb, DeviceIdentity(a.rdev)) is not None  # the adapter became something that is no USB


def _samples(n: int, counter: int) -> bytes:
    return b"".join(encode(Sample(k + 1, counter, k, -k, 1024, 0)) for k in range(n))


def _received(t, n: int, timeout_s: float = 3.0) -> int:
    got, end = 0, time.monotonic() + timeout_s
    while got < n and time.monotonic() < end:
        got += sum(len(ev) for ev in t.recv(0.05) if isinstance(ev, SampleBatch))
    return got


def _slcan_samples(n: int, counter: int) -> bytes:
    """The same SAMPLE frames as `_samples`, as an SLCAN adapter passes them on (one ``T`` line each)."""
    from protocol import to_can
    out = []
    for k in range(n):
        f = to_can(Sample(k + 1, counter, k, -k, 1024, 0))
        out.append(f"T{f.arbitration_id:08X}{len(f.data)}{f.data.hex().upper()}\r".encode())
    return b"".join(out)


#: a serial gateway's port, and an SLCAN adapter's tty: the same rule for both
PORT_KINDS = {
    "serial": (lambda link: SerialTransport(str(link), reconnect_interval_s=0.05), _samples),
    "slcan": (lambda link: CanTransport(f"slcan:{link}", bitrate=1_000_000, sleep_after_open=0, drain_quiet_s=0.02,
                                        reconnect_interval_s=0.05), _slcan_samples),
}


@pytest.mark.parametrize("kind", list(PORT_KINDS))
def test_another_pty_under_the_same_path_is_refused_never_opened(tmp_path, kind):
    """The port (a serial gateway's, or an SLCAN adapter's tty) goes away; the path now leads to
    another pty: the transport does not open it (no byte written — no SLCAN command either —, its
    terminal settings untouched: not switched to raw mode), counts and says why; when the first
    device's number is back at the path it reconnects."""
    import tty as tty_mod
    make, frames = PORT_KINDS[kind]
    link = tmp_path / "sheet"
    m1, s1 = os.openpty()
    tty_mod.setraw(m1)
    name1 = os.ttyname(s1)
    m2, s2 = os.openpty()  # the other device, made while the first is alive: another number
    os.symlink(name1, link)
    t = make(link)
    m3 = s3 = None
    try:
        assert t.identity is not None and t.identity.rdev == os.stat(name1).st_rdev
        os.write(m1, frames(3, 1))
        assert _received(t, 3) == 3
        os.close(s1)
        os.close(m1)  # the port goes away
        end = time.monotonic() + 3
        while t.stats.disconnects == 0 and time.monotonic() < end:
            t.recv(0.05)
        assert t.stats.disconnects == 1
        attrs = termios.tcgetattr(s2)
        tmp = str(link) + ".new"
        os.symlink(os.ttyname(s2), tmp)
        os.replace(tmp, link)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            t.recv(0.05)
        assert t.stats.reconnects == 0 and not t.connected and t.stats.refused_reopens >= 2
        assert t.refused is not None and "came back as another device" in t.refused and "\n" not in t.refused
        os.set_blocking(m2, False)
        with pytest.raises(BlockingIOError):
            os.read(m2, 4096)  # nothing was written into it
        assert termios.tcgetattr(s2) == attrs  # nor its settings changed
        assert holders(os.ttyname(s2)) == []  # nor is it held
        # the first device's number back at the path (a USB adapter plugged in again): reconnected
        m3, s3, name3 = open_pty(name1, wait_s=5.0)
        assert name3 == name1, "the test could not get the pty number back (another process took it)"
        tty_mod.setraw(m3)
        os.replace(link, tmp)
        os.unlink(tmp)
        os.symlink(name3, link)
        end = time.monotonic() + 3
        while t.stats.reconnects == 0 and time.monotonic() < end:
            t.recv(0.05)
        assert t.stats.reconnects == 1 and t.connected and t.refused is None
        os.write(m3, frames(4, 9))
        assert _received(t, 4) == 4
    finally:
        t.close()
        for fd in (m2, s2, m3, s3):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
