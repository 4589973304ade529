"""The interface every chip implementation of capsheet shares — the Python model
(`virtual_sheet.chip.ChipModel`) and the C reference firmware behind cffi
(`firmware_ref.chip.CFirmwareChip`) — so a virtual sheet runs on either through its ``chip_factory``.

A chip is built as ``Chip(uid, sensor, *, transport, fd, capabilities, calibration, ...)`` and driven
by ``power_on(now_s)``, ``handle(frame, now_s) -> list[Out]`` and ``tick(now_s) -> list[Out]``. Time
is always an argument (seconds); a chip never reads a clock. This module holds what both need and
neither owns: the callback and output types, the default capabilities, the constructor checks.
It does no I/O.
"""

from __future__ import annotations

from typing import Callable, Union

from .can import CanFrame
from .messages import Capability

__all__ = ["Out", "SensorSource", "ChipFactory", "DEFAULT_CAPABILITIES", "check_chip_args"]

#: One serial frame including its 0x00 delimiter, or one CAN frame.
Out = Union[bytes, CanFrame]
#: ``now_s -> ((x, y, z) ADC counts at ±2 g, SampleStatus bits)``, read by the chip at SYNC.
SensorSource = Callable[[float], tuple[tuple[int, int, int], int]]
#: What a virtual sheet calls to make each chip: ``factory(uid, sensor, **options) -> chip``.
ChipFactory = Callable[..., object]

#: INFO capability bits a chip reports unless told otherwise (CAN_FD is added for an FD chip).
DEFAULT_CAPABILITIES = (Capability.SELF_TEST | Capability.CAL_STORAGE | Capability.MULTI_RANGE
                        | Capability.FILTER)


def check_chip_args(uid: int, transport: str, calibration) -> None:
    """The constructor checks every chip implementation makes, with one wording.

    >>> check_chip_args(1, "usb", [(0, 1024)] * 3)
    Traceback (most recent call last):
    ...
    ValueError: Invalid transport: 'usb' (expected 'serial' or 'can')
    """
    if transport not in ("serial", "can"):
        raise ValueError(f"Invalid transport: {transport!r} (expected 'serial' or 'can')")
    if not (isinstance(uid, int) and 0 <= uid < 1 << 64):
        raise ValueError(f"Invalid uid: {uid!r} (need a 64-bit unsigned integer)")
    if len(calibration) != 3:
        raise ValueError(f"Invalid calibration: {calibration!r} (need 3 axes of (offset_q4, sensitivity))")
