"""What a real part on each link feels: the truth the virtual sheet computes, at an instant, for the
register emulators of virtual_sheet/parts/ (`firmware_ref.part_chip.PartChipFactory` takes it as
its ``truth``)."""

from __future__ import annotations

import math

import numpy as np

from virtual_sheet.magfield import field_in_sensor_frames

__all__ = ["SheetTruth"]


class SheetTruth:
    """Every link's specific force (m/s²), rate (rad/s) and magnetic field (T), sensor frame, at
    ``now_s``: the moving scene's exact truth (`imu_source.ImuSource`, at its grid instant), or a
    static shape's gravity (no field: zeros). A sheet without magnetometers (its ``sensors`` without
    ``mag``) has no part that feels the field: zeros too (the field was most of the cost of an instant)."""

    def __init__(self, sheet) -> None:
        self.sheet = sheet
        self._field = "mag" in getattr(sheet, "sensors", "mag")
        self._at: float | None = None
        self._value: tuple | None = None

    def at(self, now_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._at == now_s and self._value is not None:
            return self._value
        src = self.sheet.imu_source
        if src is not None:
            k = max(0, int(math.floor(now_s * src.grid_hz + 1e-9)))
            e = src.truth_at(k)
            f, w = np.asarray(e.specific_force, dtype=float), np.asarray(e.angular_velocity, dtype=float)
            if self._field:
                b = np.asarray(field_in_sensor_frames(src.imu.field, np.asarray(e.position)[None],
                                                      np.asarray(e.frames)[None])[0], dtype=float)
            else:
                b = np.zeros_like(f)
        else:
            f = self.sheet.specific_force(now_s)
            w = np.zeros_like(f)
            b = np.zeros_like(f)
        self._at, self._value = now_s, (f, w, b)
        return self._value
