"""One session per port, and a reconnect only to the same device.

**One session per port.** Two programs reading one serial port each get part of its bytes: the
frames are cut between them and both see CRC and COBS errors. So every capsheet command that opens
a serial port (a gateway, or an SLCAN adapter on a tty) takes it exclusively, with the advisory
lock pyserial's ``exclusive=True`` takes (``flock(LOCK_EX | LOCK_NB)`` on the open port, taken
before pyserial changes any setting). The lock belongs to the open port, so it goes when the
session ends, however it ends (a crash, SIGKILL). A second session finds it taken and stops with
one line naming the holder: ``/proc/locks`` gives the process that took the lock and
``/proc/<pid>/cmdline`` what it runs (`holders`, `in_use_message`). The second session looks
there *before* it opens the port at all, so a port in use is not even opened (pyserial's lock
remains the guard for two sessions starting at once).

Not used: ``TIOCEXCL``. It makes the kernel refuse every further open of the tty, but it is
cleared only at the tty's last close: a pty whose other end (the virtual sheet) keeps the slave
open, or a session killed with SIGKILL on such a tty, would leave the port unopenable for the next
session, and it says nothing about who holds it. python-can's interfaces: SocketCAN has no
exclusive mode (several programs on one ``can0`` is how SocketCAN is meant to be used: each gets
every frame), nor have ``virtual`` and ``udp_multicast``; an SLCAN adapter is a tty and is locked
as one (`host.transport.slcan`).

**The same device after a reconnect.** A port that went away (a USB adapter unplugged, a sheet
restarted) may come back as something else at the same path: a symlink now pointing to another
pty, another adapter plugged into the socket. `DeviceIdentity` is what a port was when it was
first opened: the character device's number (``st_rdev``) and, for a USB adapter, its vendor,
product and serial number (pyserial's ``serial.tools.list_ports``). `different` says what changed;
the transport reopens only when nothing did, and never opens (so never writes to, never puts into
raw mode) a device that differs.

A USB device with the same serial number that comes back under another number (``ttyACM1`` while
the old ``ttyACM0`` was still held open, behind a ``/dev/serial/by-id`` link) is refused too: the
device number is part of the identity. Give that path again to a new session.
"""

from __future__ import annotations

import errno
import os
import stat
from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["DeviceIdentity", "identify", "different", "parse_proc_locks", "holders", "in_use_message",
           "is_device_path", "usb_info", "PortBusy", "open_exclusive", "refusal"]


class PortBusy(Exception):
    """The port is held by another session; the message (`in_use_message`) names the holder."""


def is_device_path(port: str) -> bool:
    """True for a path (a device, a pty, a symlink to one); False for a pyserial URL (``loop://``,
    ``socket://...``).

    >>> is_device_path("/dev/ttyUSB0"), is_device_path("loop://"), is_device_path("socket://h:1")
    (True, False, False)
    """
    return "://" not in port


def parse_proc_locks(text: str, dev: int, ino: int) -> list[int]:
    """The process ids holding a lock on the file ``(dev, ino)`` in ``/proc/locks``' text.

    Lines read ``1: FLOCK  ADVISORY  WRITE 4242 00:1a:3 0 EOF``: the file as ``MAJ:MIN:INODE`` (major
    and minor in hex, the inode in decimal). Lines of processes waiting for a lock (``->``) are
    skipped; so is anything that does not parse.

    >>> text = "1: FLOCK  ADVISORY  WRITE 4242 00:1a:3 0 EOF\\n2: POSIX  ADVISORY  READ 7 08:01:99 0 EOF\\n"
    >>> parse_proc_locks(text, os.makedev(0, 0x1a), 3), parse_proc_locks(text, os.makedev(8, 1), 99)
    ([4242], [7])
    >>> parse_proc_locks("1: -> FLOCK  ADVISORY  WRITE 5 00:1a:3 0 EOF\\ngarbage\\n", os.makedev(0, 0x1a), 3)
    []
    """
    want = f"{os.major(dev):02x}:{os.minor(dev):02x}:{ino}"
    out: list[int] = []
    for line in text.splitlines():
        parts = line.split()
        if len(parts) < 6 or parts[1] == "->":
            continue
        try:
            pid = int(parts[4])
            maj, mnr, inode = parts[5].split(":")
            key = f"{int(maj, 16):02x}:{int(mnr, 16):02x}:{int(inode)}"
        except ValueError:
            continue
        if key == want and pid not in out:
            out.append(pid)
    return out


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            raw = f.read(4096)
    except OSError:
        return ""
    words = [w.decode("utf-8", "replace") for w in raw.split(b"\0") if w]
    text = " ".join(words)
    return text if len(text) <= 120 else text[:117] + "..."


def holders(path: str) -> list[tuple[int, str]]:
    """``(pid, command line)`` of the processes holding a lock on the device at ``path`` (symlinks
    followed), from ``/proc/locks``; ``[]`` when none does or the system does not say. A command
    line may be ``""`` (the process ended, or is another user's)."""
    try:
        st = os.stat(path)
        with open("/proc/locks", encoding="ascii", errors="replace") as f:
            text = f.read()
    except OSError:
        return []
    return [(pid, _cmdline(pid)) for pid in parse_proc_locks(text, st.st_dev, st.st_ino) if pid != os.getpid()]


def in_use_message(path: str, found: list[tuple[int, str]] | None = None) -> str:
    """The one line that says ``path`` is in use, and by which process where the system says."""
    found = holders(path) if found is None else found
    target = os.path.realpath(path)
    where = path if target == path else f"{path} (-> {target})"
    if not found:
        return (f"{where} is in use by another session (locked; the system does not say by which "
                f"process): one session per port")
    who = ", ".join(f"process {pid}" + (f" ({cmd})" if cmd else "") for pid, cmd in found)
    return f"{where} is in use by {who}: one session per port"


@dataclass(frozen=True, slots=True)
class DeviceIdentity:
    """What a port was when it was opened (module docstring).

    Attributes
    ----------
    rdev : int or None
        The character device's number (``st_rdev``), e.g. ``os.makedev(136, 3)`` for
        ``/dev/pts/3``, ``os.makedev(188, 0)`` for ``/dev/ttyUSB0``; None for what is no device.
    usb : tuple or None
        ``(vid, pid, serial_number)`` of a USB adapter (``serial_number`` may be None: many
        cheap adapters have none); None for a device that is not USB (a pty, a built-in UART).
    """

    rdev: int | None
    usb: tuple | None = None

    def describe(self) -> str:
        """
        >>> DeviceIdentity(os.makedev(136, 3)).describe()
        'device 136:3'
        >>> DeviceIdentity(os.makedev(188, 0), (0x0403, 0x6001, "A10K")).describe()
        'device 188:0, USB 0403:6001 serial A10K'
        """
        s = "no device" if self.rdev is None else f"device {os.major(self.rdev)}:{os.minor(self.rdev)}"
        if self.usb is not None:
            vid, pid, sn = self.usb
            s += f", USB {vid:04x}:{pid:04x}" + (f" serial {sn}" if sn else " (no serial number)")
        return s


def usb_info(path: str) -> tuple | None:
    """``(vid, pid, serial_number)`` of the USB adapter at ``path`` (symlinks followed) as pyserial's
    ``list_ports`` reports it; None for a device that is not USB or that it does not list."""
    try:
        from serial.tools import list_ports
        target = os.path.realpath(path)
        for p in list_ports.comports():
            if os.path.realpath(p.device) == target and p.vid is not None:
                return (int(p.vid), int(p.pid or 0), p.serial_number or None)
    except Exception:  # noqa: BLE001 - a listing that fails says nothing about identity
        return None
    return None


def identify(path: str, fd: int | None = None) -> DeviceIdentity:
    """The identity of the device at ``path`` (of the open ``fd`` when given: what was opened, not
    what the path leads to now). Raises ``OSError`` when the path leads nowhere."""
    st = os.fstat(fd) if fd is not None else os.stat(path)
    rdev = st.st_rdev if stat.S_ISCHR(st.st_mode) else None
    return DeviceIdentity(rdev, usb_info(path) if rdev is not None else None)


def different(before: DeviceIdentity, now: DeviceIdentity) -> str | None:
    """What differs between the device a port was and the one its path leads to now; None if it is
    the same device.

    >>> a = DeviceIdentity(os.makedev(188, 0), (0x0403, 0x6001, "A10K"))
    >>> different(a, a) is None
    True
    >>> different(a, DeviceIdentity(os.makedev(188, 0), (0x0403, 0x6001, "B22Q")))
    'USB serial number B22Q, not A10K'
    >>> different(DeviceIdentity(os.makedev(136, 3)), DeviceIdentity(os.makedev(136, 7)))
    'device 136:7, not 136:3'
    """
    if before.rdev != now.rdev:
        fmt = (lambda r: "none" if r is None else f"{os.major(r)}:{os.minor(r)}")
        return f"device {fmt(now.rdev)}, not {fmt(before.rdev)}"
    if before.usb != now.usb:
        if before.usb is None or now.usb is None:
            return f"{now.describe()}, not {before.describe()}"
        if before.usb[:2] != now.usb[:2]:
            return f"USB {now.usb[0]:04x}:{now.usb[1]:04x}, not {before.usb[0]:04x}:{before.usb[1]:04x}"
        return f"USB serial number {now.usb[2]}, not {before.usb[2]}"
    return None


def open_exclusive(opener: Callable[[bool | None], Any], path: str) -> tuple[Any, DeviceIdentity | None]:
    """Open the port at ``path`` for one session: ``opener(exclusive)`` opens it (pyserial's
    ``serial_for_url(..., exclusive=exclusive)``). For a device path, a port another process holds
    is refused before it is opened, and one taken meanwhile by pyserial's lock (EAGAIN), both as
    `PortBusy`; a URL is opened as it is (``exclusive=None``). Returns the port and the
    `DeviceIdentity` of what was opened (None for a URL). Other errors of ``opener`` propagate."""
    device = is_device_path(path)
    if device:
        found = holders(path)
        if found:
            raise PortBusy(in_use_message(path, found))
    try:
        port = opener(True if device else None)
    except Exception as exc:
        if device and getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK):
            raise PortBusy(in_use_message(path)) from exc
        raise
    ident = None
    if device:
        try:
            ident = identify(path, port.fileno())
        except (AttributeError, OSError, ValueError):
            ident = None
    return port, ident


def refusal(name: str, before: DeviceIdentity, now: DeviceIdentity | None) -> str | None:
    """The one line refusing a reopen of ``name`` when what its path leads to ``now`` is not the
    device it was ``before``; None when it is.

    >>> refusal("/tmp/sheet", DeviceIdentity(os.makedev(136, 3)), DeviceIdentity(os.makedev(136, 3))) is None
    True
    >>> refusal("/tmp/sheet", DeviceIdentity(os.makedev(136, 3)), DeviceIdentity(os.makedev(136, 7)))
    '/tmp/sheet came back as another device (device 136:7, not 136:3): refused, never opened; reconnecting only to the device it was'
    """
    why = different(before, now) if now is not None else "no device"
    if why is None:
        return None
    return (f"{name} came back as another device ({why}): refused, never opened; reconnecting only to "
            f"the device it was")
