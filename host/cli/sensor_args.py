"""``--sensors`` and the IMU ranges, for every command that brings 6/9-axis chips up (capsheet host,
demo, calibrate): the arguments and the CONFIG_IMU fields they ask for (docs/protocol.md §16.2)."""

from __future__ import annotations

__all__ = ["add_sensor_args", "imu_config"]


def add_sensor_args(p) -> None:
    """``--sensors`` and the IMU ranges (docs/protocol.md §16.2): what the host asks 6/9-axis chips for."""
    p.add_argument("--sensors", choices=("accel", "accel+gyro", "accel+gyro+mag"), default="accel",
                   help="what every chip sends per SYNC: accel (v1.1 SAMPLE, default), accel+gyro or "
                        "accel+gyro+mag (IMU records, CONFIG_IMU; the chips must have the sensors)")
    p.add_argument("--gyro-range", type=int, choices=(125, 250, 500, 1000, 2000), default=1000, metavar="DPS",
                   help="gyroscope full scale, °/s (125, 250, 500, 1000, 2000; default 1000)")
    p.add_argument("--mag-range", type=int, choices=(4, 8, 12, 16), default=4, metavar="GAUSS",
                   help="magnetometer full scale, gauss (4, 8, 12, 16; default 4)")


def imu_config(args) -> tuple[int, int, int, int] | None:
    """The CONFIG_IMU fields ``--sensors`` and the ranges ask for, or None for accel-only chips."""
    fmt = {"accel": 0, "accel+gyro": 1, "accel+gyro+mag": 2}[getattr(args, "sensors", "accel")]
    if fmt == 0:
        return None
    return fmt, {125: 0, 250: 1, 500: 2, 1000: 3, 2000: 4}[args.gyro_range], args.mag_range // 4 - 1, 0
