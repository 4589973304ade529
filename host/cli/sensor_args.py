"""``--sensors`` and the IMU ranges, for every command that brings 6/9-axis chips up (capsheet host,
demo, calibrate): the arguments and the CONFIG_IMU fields they ask for (docs/protocol.md §16.2)."""

from __future__ import annotations

from protocol.imu_units import GyroRange, MagRange

__all__ = ["add_sensor_args", "imu_config", "GYRO_DPS", "MAG_GAUSS", "gyro_range_code", "mag_range_code"]

#: the full scales a user names (°/s, gauss), from the range codes of docs/protocol.md §16.2
GYRO_DPS = tuple(r.full_scale_dps for r in GyroRange)
MAG_GAUSS = tuple(r.full_scale_gauss for r in MagRange)


def gyro_range_code(dps: int) -> int:
    """CONFIG_IMU's gyro_range code of a full scale in °/s (one of `GYRO_DPS`)."""
    return next(int(r) for r in GyroRange if r.full_scale_dps == dps)


def mag_range_code(gauss: int) -> int:
    """CONFIG_IMU's mag_range code of a full scale in gauss (one of `MAG_GAUSS`)."""
    return next(int(r) for r in MagRange if r.full_scale_gauss == gauss)


def add_sensor_args(p) -> None:
    """``--sensors`` and the IMU ranges (docs/protocol.md §16.2): what the host asks 6/9-axis chips for."""
    p.add_argument("--sensors", choices=("accel", "accel+gyro", "accel+gyro+mag"), default="accel",
                   help="what every chip sends per SYNC: accel (v1.1 SAMPLE, default), accel+gyro or "
                        "accel+gyro+mag (IMU records, CONFIG_IMU; the chips must have the sensors)")
    p.add_argument("--gyro-range", type=int, choices=GYRO_DPS, default=1000, metavar="DPS",
                   help="gyroscope full scale, °/s (125, 250, 500, 1000, 2000; default 1000)")
    p.add_argument("--mag-range", type=int, choices=MAG_GAUSS, default=4, metavar="GAUSS",
                   help="magnetometer full scale, gauss (4, 8, 12, 16; default 4)")


def imu_config(args) -> tuple[int, int, int, int] | None:
    """The CONFIG_IMU fields ``--sensors`` and the ranges ask for, or None for accel-only chips."""
    fmt = {"accel": 0, "accel+gyro": 1, "accel+gyro+mag": 2}[getattr(args, "sensors", "accel")]
    if fmt == 0:
        return None
    return fmt, gyro_range_code(args.gyro_range), mag_range_code(args.mag_range), 0
