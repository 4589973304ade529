"""Gyroscope and magnetometer ranges, and their counts <-> SI conversions (6/9-axis chips).

The accelerometer's are in `protocol.constants` (12-bit counts, ``Range``, `counts_to_si`); these
follow the same rule for the two new sensors: a ``bits``-bit two's-complement count at a
configured full-scale range ``FS``, nominal sensitivity ``2^(bits−1) / FS`` counts per unit,
a per-chip calibration refining it (``offset`` in counts, ``sensitivity`` in counts per unit)::

    value [unit] = (counts − offset) / sensitivity

Units on the wire follow the datasheets (°/s, gauss); the SI functions return rad/s and tesla.
They are the one place the simulator and the protocol (docs/protocol.md §16.1: the IMU
record's 16-bit gyroscope and magnetometer counts at CONFIG_IMU's range codes) take the conversion from.

>>> gyro_nominal_sensitivity(GyroRange.DPS2000)   # 16-bit counts per °/s
16.384
>>> round(float(gyro_counts_to_si(16384, GyroRange.DPS2000)), 6)   # 1000 °/s in rad/s
17.453293
>>> mag_nominal_sensitivity(MagRange.GAUSS4)        # counts per gauss
8192.0
>>> float(mag_counts_to_si(8192, MagRange.GAUSS4))   # 1 gauss = 100 µT
0.0001
"""

from __future__ import annotations

import math
from enum import IntEnum

__all__ = ["GYRO_BITS", "MAG_BITS", "GyroRange", "MagRange", "RAD_PER_DEG", "TESLA_PER_GAUSS",
           "count_limits", "gyro_nominal_sensitivity", "mag_nominal_sensitivity", "gyro_counts_to_si",
           "si_to_gyro_counts", "mag_counts_to_si", "si_to_mag_counts", "nominal_imu_cal",
           "corrected_gyro_counts", "corrected_mag_counts", "accel_g_of_counts"]

GYRO_BITS = 16  #: width of one gyroscope axis sample (the parts' native output: ICM-42688-P, BMI270)
MAG_BITS = 16  #: width of one magnetometer axis sample (LIS3MDL; 18-bit parts are rounded to 16)
RAD_PER_DEG = math.pi / 180.0
TESLA_PER_GAUSS = 1e-4


class GyroRange(IntEnum):
    """Gyroscope full-scale range code: ±125 · 2^code °/s."""

    DPS125 = 0  #: ±125 °/s, 262.144 counts per °/s at 16 bits
    DPS250 = 1  #: ±250 °/s
    DPS500 = 2  #: ±500 °/s
    DPS1000 = 3  #: ±1000 °/s
    DPS2000 = 4  #: ±2000 °/s, 16.384 counts per °/s at 16 bits

    @property
    def full_scale_dps(self) -> int:
        return 125 << int(self)


class MagRange(IntEnum):
    """Magnetometer full-scale range code: ±4 · (code + 1) gauss (the LIS3MDL's four ranges)."""

    GAUSS4 = 0  #: ±4 gauss (±400 µT), 8192 counts per gauss at 16 bits
    GAUSS8 = 1  #: ±8 gauss
    GAUSS12 = 2  #: ±12 gauss
    GAUSS16 = 3  #: ±16 gauss, 2048 counts per gauss at 16 bits

    @property
    def full_scale_gauss(self) -> int:
        return 4 * (int(self) + 1)


def count_limits(bits: int) -> tuple[int, int]:
    """``(min, max)`` of a ``bits``-bit two's-complement count.

    >>> count_limits(16)
    (-32768, 32767)
    """
    if not (isinstance(bits, int) and 2 <= bits <= 32):
        raise ValueError(f"Invalid bits: {bits!r} (need an integer 2..32)")
    return -(1 << (bits - 1)), (1 << (bits - 1)) - 1


def gyro_nominal_sensitivity(range_code: int = GyroRange.DPS2000, bits: int = GYRO_BITS) -> float:
    """Counts per °/s: ``2^(bits−1) / full_scale_dps``."""
    return float(1 << (bits - 1)) / GyroRange(range_code).full_scale_dps


def mag_nominal_sensitivity(range_code: int = MagRange.GAUSS4, bits: int = MAG_BITS) -> float:
    """Counts per gauss: ``2^(bits−1) / full_scale_gauss``."""
    return float(1 << (bits - 1)) / MagRange(range_code).full_scale_gauss


def gyro_counts_to_si(counts, range_code: int = GyroRange.DPS2000, offset=0.0, sensitivity=None,
                      bits: int = GYRO_BITS):
    """Gyroscope counts -> angular rate in rad/s: ``(counts − offset) / sensitivity`` °/s.

    ``sensitivity`` (counts per °/s) defaults to the range's nominal one; scalars and numpy arrays
    alike (``offset``/``sensitivity`` broadcast per axis)."""
    s = gyro_nominal_sensitivity(range_code, bits) if sensitivity is None else sensitivity
    return (counts - offset) / s * RAD_PER_DEG


def si_to_gyro_counts(rate_rps, range_code: int = GyroRange.DPS2000, offset=0.0, sensitivity=None,
                      bits: int = GYRO_BITS):
    """rad/s -> ideal (unrounded, unclipped) counts; inverse of `gyro_counts_to_si`."""
    s = gyro_nominal_sensitivity(range_code, bits) if sensitivity is None else sensitivity
    return rate_rps / RAD_PER_DEG * s + offset


def mag_counts_to_si(counts, range_code: int = MagRange.GAUSS4, offset=0.0, sensitivity=None,
                     bits: int = MAG_BITS):
    """Magnetometer counts -> flux density in tesla: ``(counts − offset) / sensitivity`` gauss."""
    s = mag_nominal_sensitivity(range_code, bits) if sensitivity is None else sensitivity
    return (counts - offset) / s * TESLA_PER_GAUSS


def si_to_mag_counts(field_t, range_code: int = MagRange.GAUSS4, offset=0.0, sensitivity=None,
                     bits: int = MAG_BITS):
    """Tesla -> ideal (unrounded, unclipped) counts; inverse of `mag_counts_to_si`."""
    s = mag_nominal_sensitivity(range_code, bits) if sensitivity is None else sensitivity
    return field_t / TESLA_PER_GAUSS * s + offset


# ---------------------------------------------------------------------------------------------
# new in 1.3 (docs/protocol.md §17): the gyroscope's and magnetometer's calibration, applied on the chip
# ---------------------------------------------------------------------------------------------

_NOMINAL = {0: (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 1: (0.0,) * 3, 2: (0.0,) * 9,
            3: (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 4: (0.0,) * 3}


def nominal_imu_cal() -> dict:
    """The §17.1 nominal calibration, block -> list of values (GYRO_MATRIX 9, GYRO_BIAS 3, GYRO_G_SENS
    9, MAG_MATRIX 9, MAG_HARD_IRON 3; matrices row-major): identity matrices, zero vectors."""
    return {b: list(v) for b, v in _NOMINAL.items()}


def _clamp_round(x):
    """Round to nearest, halves away from zero (as C's ``(int)(v + 0.5)`` on |v|), then clamp."""
    import numpy as np
    return np.clip(np.sign(x) * np.floor(np.abs(x) + 0.5), -32768, 32767).astype(np.int64)


def corrected_gyro_counts(counts, range_code, matrix, bias_rps, g_sens, accel_g):
    """§17.3: the gyroscope counts a calibrated chip sends, ``(m, 3)`` int64:
    ``round(A (c − s (b + Γ f)))`` with ``s`` the counts per rad/s at the range.

    ``counts (m, 3)`` as read at ``range_code (m,)`` (or a scalar), ``matrix (m, 3, 3)``, ``bias_rps
    (m, 3)``, ``g_sens (m, 3, 3)`` (rad/s per g), ``accel_g (m, 3)``: the same record's accelerometer
    counts sent, scaled to ±2 g counts, over the nominal 1024 counts per g (`accel_g_of_counts`).

    >>> import numpy as np
    >>> I = np.eye(3)[None]; z = np.zeros((1, 3))
    >>> corrected_gyro_counts([[100, -200, 3000]], 3, I, z, 0 * I, z).tolist()
    [[100, -200, 3000]]
    >>> corrected_gyro_counts([[100, -200, 3000]], 3, 2 * I, z, 0 * I, z).tolist()
    [[200, -400, 6000]]
    """
    import numpy as np
    c = np.asarray(counts, dtype=float)
    r = np.broadcast_to(np.asarray(range_code, dtype=np.int64), c.shape[:1])
    s = (float(1 << (GYRO_BITS - 1)) / (125.0 * np.exp2(r)))[:, None] / RAD_PER_DEG  # counts per rad/s
    off = np.asarray(bias_rps, dtype=float) + np.einsum("kij,kj->ki", np.asarray(g_sens, dtype=float),
                                                        np.asarray(accel_g, dtype=float))
    return _clamp_round(np.einsum("kij,kj->ki", np.asarray(matrix, dtype=float), c - s * off))


def accel_g_of_counts(counts, range_code):
    """§17.3's ``f``: accelerometer counts sent at CONFIG range code ``range_code``, in g at the
    nominal ±2 g sensitivity (1024 counts per g; the chip's CAL_DATA is not applied)."""
    import numpy as np
    return np.asarray(counts, dtype=float) * np.exp2(np.asarray(range_code, dtype=float))[..., None] / 1024.0


def corrected_mag_counts(counts, range_code, matrix, hard_iron_t):
    """§17.3: the magnetometer counts a calibrated chip sends, ``(m, 3)`` int64:
    ``round(S (c − s h))`` with ``s`` the counts per tesla at the range.

    >>> import numpy as np
    >>> corrected_mag_counts([[8192, 0, -8192]], 0, np.eye(3)[None], [[1e-4, 0.0, 0.0]]).tolist()
    [[0, 0, -8192]]
    """
    import numpy as np
    c = np.asarray(counts, dtype=float)
    r = np.broadcast_to(np.asarray(range_code, dtype=np.int64), c.shape[:1])
    s = (float(1 << (MAG_BITS - 1)) / (4.0 * (r + 1)))[:, None] / TESLA_PER_GAUSS  # counts per tesla
    return _clamp_round(np.einsum("kij,kj->ki", np.asarray(matrix, dtype=float),
                                  c - s * np.asarray(hard_iron_t, dtype=float)))
