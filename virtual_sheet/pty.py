"""Pseudo-terminals the virtual sheet serves its host through: opening one (`open_pty`), the stable
symlink a device publishes and may take back from a killed sheet only (`claim_symlink`, with its
records in `SYMLINK_RECORDS`), one pty end's reads and writes (`PtyEndpoint`, `PtyPort`) and several
served with one ``select`` (`PtyGroup`). The devices of virtual_sheet/devices.py are built on them."""

from __future__ import annotations

import hashlib
import json
import os
import select
import tempfile
import time
import tty
from typing import Callable

__all__ = ["SYMLINK_RECORDS", "claim_symlink", "open_pty", "PtyEndpoint", "PtyPort", "PtyGroup"]


#: where the record of every symlink a device publishes is kept (one small JSON file per path)
SYMLINK_RECORDS = os.path.join(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir(),
                               f"capsheet-symlinks-{os.getuid()}")


def _record_file(path: str) -> str:
    return os.path.join(SYMLINK_RECORDS, hashlib.sha256(os.path.abspath(path).encode()).hexdigest()[:24] + ".json")


def _read_record(path: str) -> dict | None:
    try:
        with open(_record_file(path)) as fh:
            rec = json.load(fh)
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and rec.get("path") == os.path.abspath(path) else None


def _write_record(path: str, target: str) -> None:
    os.makedirs(SYMLINK_RECORDS, mode=0o700, exist_ok=True)
    tmp = _record_file(path) + f".{os.getpid()}"
    with open(tmp, "w") as fh:
        json.dump({"path": os.path.abspath(path), "target": target, "pid": os.getpid()}, fh)
    os.replace(tmp, _record_file(path))


def _drop_record(path: str) -> None:
    rec = _read_record(path)
    if rec is not None and rec.get("pid") == os.getpid():
        try:
            os.unlink(_record_file(path))
        except FileNotFoundError:
            pass


def _alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, ValueError, TypeError):
        return True  # it exists (another user's), or we cannot tell: do not take its path
    return True


def claim_symlink(path: str | os.PathLike, *, replace: bool = False) -> None:
    """Check that a device may publish its symlink at ``path`` (module docstring, "Whose path it
    is"): nothing there, or a stale symlink a capsheet device published (replaced when the device
    starts). ``replace`` (the user said so): a file or a foreign symlink there is removed now.

    Raises
    ------
    FileExistsError
        ``path`` is a folder, the live port of another running sheet, or (without ``replace``) a
        file or a symlink no capsheet device published. The message says which.
    """
    path = os.fspath(path)
    if not os.path.lexists(path):
        return
    if os.path.isdir(path) and not os.path.islink(path):
        raise FileExistsError(f"{path} is a folder: a port symlink cannot take its place (give another path)")
    if os.path.islink(path):
        target, rec = os.readlink(path), _read_record(path)
        if rec is not None and rec.get("target") == target:
            if rec.get("pid") != os.getpid() and _alive(rec.get("pid")):
                raise FileExistsError(f"{path} is the port of a running virtual sheet (pid {rec['pid']}): stop it "
                                      f"or give another path")
            return  # a stale symlink of ours (its sheet was killed): replaced at start
        what = f"a symlink to {target} that no capsheet sheet published"
    else:
        what = "a file"
    if not replace:
        raise FileExistsError(f"{path} is {what}: not replaced (--overwrite replaces it)")
    os.unlink(path)


def _pty_index(path: str) -> int:
    try:
        return int(os.path.basename(path))
    except ValueError:
        return -1


def open_pty(want: str | None = None, wait_s: float = 1.0) -> tuple[int, int, str]:
    """A raw pseudo-terminal: ``(master_fd, slave_fd, slave_path)``, master non-blocking.

    ``want``: the slave path a pty of this device had before (a bus back from an outage): the same
    one if it comes free within ``wait_s``, as a USB adapter plugged back in keeps its number (a
    host reconnects only to the same device, host/transport/portlock.py). The kernel hands out the
    lowest free number: lower ones are held while asking, a higher one means ``want`` is still
    held (by a host that has not closed it yet) and is asked again; after ``wait_s`` whatever came.
    """
    held: list[tuple[int, int]] = []
    end = time.monotonic() + wait_s
    try:
        while True:
            master, slave = os.openpty()
            name = os.ttyname(slave)
            if want is None or name == want or time.monotonic() >= end or len(held) >= 256:
                break
            if 0 <= _pty_index(name) < _pty_index(want):
                held.append((master, slave))  # a lower number is free: keep it while asking again
            else:
                os.close(slave)
                os.close(master)
                time.sleep(0.01)
    finally:
        for fds in held:
            for fd in fds:
                os.close(fd)
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, name


class PtyEndpoint:
    """A pty with a stable symlink, re-created after an outage (module docstring)."""

    def pty_init(self, symlink_path: str | os.PathLike | None) -> None:
        self._tmpdir = None
        if symlink_path is None:
            self._tmpdir = tempfile.mkdtemp(prefix="capsheet-")
            symlink_path = os.path.join(self._tmpdir, self.name)
        else:
            claim_symlink(symlink_path)  # nothing there but (at most) a stale symlink of ours
        self.path = str(symlink_path)
        self.tty: str | None = None
        self._master = self._slave = -1
        # through an outage the slave side stays open here: the pty's number stays taken while the
        # master is closed (the host's reads fail all the same), so that no other process on the
        # machine takes it meanwhile and the bus comes back under its number, as a USB adapter
        # plugged in again does (a host reconnects only to the same device)
        self._reserved = -1
        self._pending = bytearray()
        self.tx_overflow_bytes = 0
        self.tx_overflow_frames = 0  #: frames dropped whole because the host did not read (counted)
        # what a gateway holds for a host that does not read: a real adapter's buffer is small, and
        # a bounded one lets a host that fell behind see fresh frames again (newest wins)
        self.max_pending = 256 << 10

    def _release_number(self) -> None:
        if self._reserved >= 0:
            try:
                os.close(self._reserved)
            except OSError:
                pass
            self._reserved = -1

    def pty_open(self) -> None:
        # back from an outage: the same pty number, held until now, asked for at once (open_pty)
        self._release_number()
        self._master, self._slave, self.tty = open_pty(self.tty)
        claim_symlink(self.path)  # still nothing but (at most) a stale symlink of ours there
        # a name of our own beside it, then one atomic rename: a host reopening the path never
        # finds it missing, and nothing else's file is touched
        tmp = os.path.join(os.path.dirname(os.path.abspath(self.path)),
                           f".{os.path.basename(self.path)}.capsheet-{os.getpid()}-{id(self):x}")
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(self.tty, tmp)
        os.replace(tmp, self.path)
        if self._tmpdir is None:
            _write_record(self.path, self.tty)

    def pty_close(self, remove_link: bool = True) -> None:
        """Close the pty (an outage): the master goes, so the host's reads fail; the slave side is
        kept open until `pty_open` or `pty_cleanup`, holding the pty's number."""
        self._release_number()
        if self._master >= 0:
            try:
                os.close(self._master)
            except OSError:
                pass
        self._reserved = self._slave
        self._master = self._slave = -1
        self._pending.clear()
        if remove_link:
            try:
                if self.tty is not None and os.readlink(self.path) == self.tty:  # still ours
                    os.unlink(self.path)
            except OSError:  # gone, or no longer a symlink: someone else's now
                pass
            if self._tmpdir is None:
                _drop_record(self.path)

    @property
    def master(self) -> int:
        """The master side's file descriptor (-1 while closed)."""
        return self._master

    @property
    def has_pending(self) -> bool:
        """Bytes wait for the host to read them (write again when the master is writable)."""
        return bool(self._pending)

    def pty_read(self, timeout_s: float) -> bytes:
        if self._master < 0:
            time.sleep(timeout_s)
            return b""
        wl = [self._master] if self._pending else []
        r, w, _ = select.select([self._master], wl, [], timeout_s)
        if w:
            self.pty_write(b"")
        if not r:
            return b""
        try:
            return os.read(self._master, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:  # EIO: no slave open right now
            time.sleep(min(timeout_s, 0.005))
            return b""

    def pty_write(self, data: bytes, n_frames: int = 0) -> None:
        if self._master < 0:
            return
        if data:
            if len(self._pending) + len(data) > self.max_pending:
                self.tx_overflow_bytes += len(data)  # nobody reads: the frames fall on the floor whole
                self.tx_overflow_frames += n_frames
                return
            self._pending += data
        while self._pending:
            try:
                n = os.write(self._master, self._pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.tx_overflow_bytes += len(self._pending)
                self._pending.clear()
                return
            del self._pending[:n]

    def pty_cleanup(self) -> None:
        self.pty_close()
        self._release_number()
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass


class PtyPort(PtyEndpoint):
    """One pseudo-terminal with a stable symlink, re-created after an outage: for a device that
    serves several of its own (the SLCAN adapters of virtual_sheet/slcan.py)."""

    def __init__(self, name: str, symlink_path: str | os.PathLike | None = None) -> None:
        self.name = name
        self.pty_init(symlink_path)

    def open(self) -> None:
        self.pty_open()

    def close(self, remove_link: bool = True) -> None:
        self.pty_close(remove_link)

    def cleanup(self) -> None:
        self.pty_cleanup()

    def write(self, data: bytes, n_frames: int = 0) -> None:
        """Queue ``data`` (``n_frames`` frames) for the host and write what the pty takes."""
        self.pty_write(data, n_frames)


class PtyGroup:
    """Several `PtyPort` s served as one: one ``select`` over their masters, each port's bytes
    handed on with its index. What a device with a pty per gateway (`MultiPtyDevice`) or per CAN
    bus (virtual_sheet/slcan.py's `SlcanDevice`) serves its host through.

    ``group[b]`` is port ``b``; ``group.paths`` their stable symlinks (``symlink_paths``, else
    each in a private temporary directory, named ``f"{prefix}{b}"``).
    """

    def __init__(self, prefix: str, n: int, symlink_paths: list[str] | None = None) -> None:
        self.ports = [PtyPort(f"{prefix}{b}", symlink_paths[b] if symlink_paths else None) for b in range(n)]
        self.paths = [p.path for p in self.ports]

    def __len__(self) -> int:
        return len(self.ports)

    def __getitem__(self, b: int) -> PtyPort:
        return self.ports[b]

    def __iter__(self):
        return iter(self.ports)

    @property
    def tx_overflow_frames(self) -> int:
        """Frames dropped whole, over every port, because the host did not read (counted)."""
        return sum(p.tx_overflow_frames for p in self.ports)

    def open(self) -> None:
        for p in self.ports:
            p.open()

    def close(self) -> None:
        """Close every port (an outage): the symlinks go until `open`."""
        for p in self.ports:
            p.close()

    def cleanup(self) -> None:
        for p in self.ports:
            p.cleanup()

    def serve(self, timeout_s: float, on_data: Callable[[int, bytes, float], None],
              clock: Callable[[], float]) -> None:
        """Wait at most ``timeout_s`` for the host: write what waits where a port takes it, and
        hand what a port received to ``on_data(index, data, t)``, ``t`` the ``clock`` when it was read.

        Every ready port is read (and stamped) before any ``on_data``: the host writes a SYNC to
        every port at once, and a port's bytes arrive when they are read, not after the other
        ports' answers were made (a chip samples when its SYNC arrives, docs/motion.md)."""
        fds = {p.master: b for b, p in enumerate(self.ports) if p.master >= 0}
        if not fds:
            time.sleep(timeout_s)
            return
        wl = [p.master for p in self.ports if p.has_pending and p.master >= 0]
        r, w, _ = select.select(list(fds), wl, [], timeout_s)
        for fd in w:
            self.ports[fds[fd]].write(b"")
        got = []
        for fd in r:
            try:
                data = os.read(fd, 65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:  # EIO: no slave open right now
                continue
            if data:
                got.append((fds[fd], data, clock()))
        for b, data, t in got:
            on_data(b, data, t)
