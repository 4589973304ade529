"""An in-memory, thread-safe byte link: the fast transport for unit tests (no pty, no bus).

``a, b = memory_link()`` gives two ends; bytes written to one are read from the other, in order,
like the two sides of a serial cable. The API is the subset of pyserial's ``Serial`` the host
uses (``write``, ``read(size)`` honouring ``timeout``, ``in_waiting``, ``close``, ``is_open``), so
the host's serial transport runs on it unchanged.

A link's end can also be published under a name (`publish`) and opened by pyserial as the URL
``memory://NAME`` once `URL_HANDLERS` is in ``serial.protocol_handler_packages`` (pyserial's own
extension point for URL schemes, virtual_sheet/serial_urls/): so a program that takes a port by
name (``capsheet host --port memory://sheet``) reaches a sheet in its own process.
"""

from __future__ import annotations

import threading
import time

__all__ = ["MemoryEnd", "memory_link", "publish", "published", "URL_HANDLERS"]

#: the package to add to ``serial.protocol_handler_packages`` for ``memory://NAME``
URL_HANDLERS = "virtual_sheet.serial_urls"
_PUBLISHED: dict = {}  # name -> MemoryEnd


class _Pipe:
    def __init__(self) -> None:
        self.buf = bytearray()
        self.cond = threading.Condition()
        self.closed = False


class MemoryEnd:
    """One end of a `memory_link`. ``timeout`` (seconds, None = block) applies to `read`."""

    def __init__(self, rx: _Pipe, tx: _Pipe, name: str, timeout: float | None = 0.1) -> None:
        self._rx, self._tx = rx, tx
        self.name = self.port = name
        self.timeout = timeout
        self.bytes_written = 0

    @property
    def is_open(self) -> bool:
        return not (self._rx.closed or self._tx.closed)

    @property
    def in_waiting(self) -> int:
        return len(self._rx.buf)

    def write(self, data: bytes) -> int:
        if self._tx.closed:
            raise OSError(f"memory link {self.name!r} is closed")
        with self._tx.cond:
            self._tx.buf += data
            self._tx.cond.notify_all()
        self.bytes_written += len(data)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes; waits up to ``timeout`` for the first byte. Raises OSError once the
        link is closed and drained (as a vanished serial port does)."""
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        with self._rx.cond:
            while not self._rx.buf:
                if self._rx.closed:
                    raise OSError(f"memory link {self.name!r} is closed")
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return b""
                self._rx.cond.wait(remaining)
            out = bytes(self._rx.buf[:size])
            del self._rx.buf[:size]
            return out

    def read_all(self) -> bytes:
        return self.read(max(1, self.in_waiting)) if self.in_waiting else b""

    def close(self) -> None:
        for p in (self._rx, self._tx):
            with p.cond:
                p.closed = True
                p.cond.notify_all()

    def __enter__(self) -> "MemoryEnd":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def memory_link(name: str = "mem", timeout: float | None = 0.1) -> tuple[MemoryEnd, MemoryEnd]:
    """Two connected ends ``(host_end, device_end)``."""
    p, q = _Pipe(), _Pipe()
    return MemoryEnd(p, q, f"{name}:host", timeout), MemoryEnd(q, p, f"{name}:device", timeout)


def publish(name: str, end: MemoryEnd) -> str:
    """Make ``end`` what pyserial opens as ``memory://NAME``; returns that URL."""
    if not name or "/" in name:
        raise ValueError(f"Invalid memory link name: {name!r} (need a non-empty name without '/')")
    _PUBLISHED[name] = end
    return f"memory://{name}"


def published(url: str) -> MemoryEnd:
    """The end published for ``memory://NAME``; ``OSError`` naming it if there is none (or it was
    closed: a vanished port)."""
    name = url.split("://", 1)[1] if "://" in url else url
    end = _PUBLISHED.get(name)
    if end is None or not end.is_open:
        raise OSError(f"no memory link published as {url!r} in this process")
    return end
