"""A serial port read by a process of its own (``capsheet host --reader-processes``, docs/host.md).

A tty hands a reader at most 4,095 bytes per read and holds ~14 KB between writer and reader
(Linux's n_tty line discipline; a pty measured so). One 12 Mbaud gateway at 145 Hz brings
~8 KB per SYNC period (6.9 ms), so its port must be read every ~2-3 ms and the writer blocks
after ~11 ms without a read. With five gateways read by five threads of one interpreter, a
thread that waits for the interpreter lock (or for a core, on a loaded machine) falls behind;
every frame then reaches the aggregator after its counter's deadline, and a reader at 4 KB a
read has little headroom to catch up (a 64x64 sheet on five ptys).

`ReaderPort` puts a small process between the port and the host: it sleeps in ``select`` on
the port and copies what arrives (a burst gathered for `GATHER_S`) into a pipe of 1 MB
(``F_SETPIPE_SZ``); no interpreter
lock, no GIL hand-off, woken by the kernel as soon as bytes are there. The host reads the pipe in
reads of up to 64 KB, so its receive thread takes a whole SYNC period's bytes per read. Writes
(SYNC, commands) go to the port directly from the host, as before. The process runs
``python -S -c`` (`_PUMP`): nothing imported beyond ``os``/``select``.

`ReaderPort` has the part of pyserial's API `host.transport.ports.SerialTransport` uses (``read``,
``write``, ``in_waiting``, ``timeout``, ``close``); the port going away ends the reader, its pipe
reports end of file, and `read` raises ``serial.SerialException`` as pyserial does for a vanished
device, so the transport's reconnect logic runs unchanged.
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import subprocess
import sys
import termios

__all__ = ["ReaderPort", "PIPE_SIZE", "GATHER_S"]

#: the pipe between reader and host, bytes (Linux's default pipe-max-size): ~0.9 s of a full
#: 12 Mbaud link
PIPE_SIZE = 1 << 20
_F_SETPIPE_SZ = 1031
#: after the first bytes of a burst the reader waits this long, then drains the port (4 KB a read)
#: and writes the whole burst to the pipe at once: one read and one ingest in the host per SYNC
#: and port instead of one per 4 KB (64x64 on five gateways at 145 Hz, --record, load ~3.5:
#: complete 93.5 % without, 99.85-99.9 % with 0.5 ms; 1 ms 99.2 %; benchmarks/bench_live.py
#: --only 64x64-packed-5gw-record --design processes, one run each)
GATHER_S = 0.0005

#: the reader process: copy the port (fd argv[1], non-blocking as pyserial opened it) into the
#: pipe (fd argv[2]) until either goes away
_PUMP = r"""
import os, select, sys, time
src, dst = int(sys.argv[1]), int(sys.argv[2])
GATHER = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
os.set_blocking(dst, True)
try:
    while True:
        r, _, x = select.select([src], [], [src], 1.0)
        if not r and not x:
            if os.getppid() == 1:
                break
            continue
        try:
            d = os.read(src, 65536)
        except BlockingIOError:
            continue
        if not d:
            break
        if GATHER:  # a burst (a SYNC's answers) comes in 4 KB reads: gather it, one write
            time.sleep(GATHER)
        while len(d) < 262144:
            try:
                more = os.read(src, 65536)
            except BlockingIOError:
                break
            if not more:
                break
            d += more
        v = memoryview(d)
        while v:
            v = v[os.write(dst, v):]
except OSError:
    pass
"""


class ReaderPort:
    """``port`` (an open pyserial port with a file descriptor) read through a reader process.

    Parameters
    ----------
    port : serial.Serial
        Open; its ``fileno()`` is handed to the reader. Written and closed through this object.
    """

    def __init__(self, port) -> None:
        fd = port.fileno()
        self._port = port
        self.name = getattr(port, "port", None) or getattr(port, "name", "")
        r, w = os.pipe()
        try:
            fcntl.fcntl(w, _F_SETPIPE_SZ, PIPE_SIZE)
        except OSError:  # an older kernel or a lower pipe-max-size: the default 64 KB still works
            pass
        self._proc = subprocess.Popen([sys.executable, "-S", "-c", _PUMP, str(fd), str(w), repr(GATHER_S)], pass_fds=(fd, w),
                                      stdin=subprocess.DEVNULL, close_fds=True)
        os.close(w)
        self._r = r
        self.timeout: float | None = 0.05  #: read timeout, s (None: wait), as pyserial's
        self.bytes_read = 0

    @property
    def pid(self) -> int:
        return self._proc.pid

    def fileno(self) -> int:
        return self._r

    @property
    def in_waiting(self) -> int:
        if self._r < 0:
            raise _serial_error("port closed")
        return struct.unpack("I", fcntl.ioctl(self._r, termios.FIONREAD, b"\0\0\0\0"))[0]

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes: what the pipe holds, waiting up to ``timeout`` for the first."""
        if self._r < 0:
            raise _serial_error("port closed")
        if self.timeout != 0:
            r, _, _ = select.select([self._r], [], [], self.timeout)
            if not r:
                return b""
        elif not self.in_waiting:
            return b""
        data = os.read(self._r, size)
        if not data:  # the reader ended: the port went away (EIO) or was closed
            raise _serial_error(f"device reports readiness to read but returned no data "
                                f"(reader process of {self.name} ended)")
        self.bytes_read += len(data)
        return data

    def write(self, data: bytes) -> int | None:
        return self._port.write(data)

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        if self._r >= 0:
            os.close(self._r)
            self._r = -1
        self._port.close()


def _serial_error(msg: str) -> Exception:
    import serial
    return serial.SerialException(msg)
