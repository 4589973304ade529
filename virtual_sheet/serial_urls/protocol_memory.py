"""``memory://NAME``: the host's end of an in-memory link published in this process
(`virtual_sheet.memport.publish`), as pyserial's ``serial_for_url`` opens a URL: ``Serial(None,
**settings)``, then ``port = url`` and ``open()``. Baud rate and the other line settings mean
nothing on a memory link and are kept, not applied."""

from __future__ import annotations

from virtual_sheet.memport import published

__all__ = ["Serial"]


class Serial:
    """The pyserial API the host uses, over a published `virtual_sheet.memport.MemoryEnd`."""

    def __init__(self, port=None, baudrate: int = 9600, timeout: float | None = None, **settings) -> None:
        self.port = port
        self.baudrate = baudrate
        self.settings = settings
        self._timeout = timeout
        self._end = None

    def open(self) -> None:
        self._end = published(str(self.port))
        self._end.timeout = self._timeout

    @property
    def name(self) -> str:
        return str(self.port)

    @property
    def is_open(self) -> bool:
        return self._end is not None and self._end.is_open

    @property
    def timeout(self) -> float | None:
        return self._timeout

    @timeout.setter
    def timeout(self, value: float | None) -> None:
        self._timeout = value
        if self._end is not None:
            self._end.timeout = value

    @property
    def in_waiting(self) -> int:
        return self._end.in_waiting

    def read(self, size: int = 1) -> bytes:
        return self._end.read(size)

    def write(self, data: bytes) -> int:
        return self._end.write(data)

    def close(self) -> None:
        if self._end is not None:
            self._end.close()
