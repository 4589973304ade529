"""A robot of several sheets: the TOML file ``capsheet view --config robot.toml`` reads (docs/distribution.md
"Several sheets in one view"). Sans I/O but for `load_robot` reading the file.

    [view]                       # optional, every key optional
    frame = "base_link"          # the fixed frame the sheets are placed in (default "world")
    port = 8765                  # the live view's port (Foxglove WebSocket)
    rate = 20.0                  # scene updates per sheet per second
    endpoint = "tcp/192.168.1.10:7447"   # a Zenoh router; default peer mode on loopback

    [[sheet]]
    name = "left_forearm"        # --sheet-name of its host
    translation = [0.25, 0.10, 0.90]     # metres, in frame
    rotation = [0.0, 0.0, 0.0, 1.0]      # unit quaternion x, y, z, w ...
    # rpy_deg = [0.0, 90.0, 0.0]         # ... or roll, pitch, yaw in degrees (fixed axes x, y, z)

A sheet's pose is the transform from ``frame`` to the sheet's frame (named as the sheet), in which
its estimate's joints are drawn (the estimator's frame, docs/estimator.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from protocol.files import loads_toml, read_file

__all__ = ["SheetPose", "Robot", "load_robot", "parse_robot", "quaternion_from_rpy"]

VIEW_KEYS = {"frame", "port", "rate", "endpoint"}
SHEET_KEYS = {"name", "translation", "rotation", "rpy_deg"}
#: a quaternion's norm may be off by this much (rounded decimals) and is then normalised
QUATERNION_TOLERANCE = 1e-3
#: sheets one view draws at most (each is a Zenoh subscription and two channels)
MAX_SHEETS = 256
#: a sheet placed further than this from the fixed frame, in metres, is a typo or a hostile file
MAX_TRANSLATION_M = 1000.0
#: a robot config larger than this is refused unread
MAX_CONFIG_BYTES = 1 << 20


@dataclass(frozen=True)
class SheetPose:
    name: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]  #: unit quaternion x, y, z, w


@dataclass(frozen=True)
class Robot:
    sheets: tuple[SheetPose, ...]
    frame: str = "world"
    port: int | None = None
    rate: float | None = None
    endpoint: str | None = None


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """Radians, fixed axes (R = Rz(yaw) Ry(pitch) Rx(roll), as ROS's RPY) -> (x, y, z, w).

    >>> [round(v, 4) for v in quaternion_from_rpy(0.0, math.pi / 2, 0.0)]
    [0.0, 0.7071, 0.0, 0.7071]
    """
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def _numbers(value, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise ValueError(f"{what} must be {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def parse_robot(doc: dict, where: str = "robot config") -> Robot:
    """A TOML document (`tomllib.loads`) -> `Robot`; ValueError naming what is wrong and where."""
    from host.publish.zenoh_pub import LOCATOR, SHEET_NAME

    unknown = set(doc) - {"view", "sheet"}
    if unknown:
        raise ValueError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(sorted(unknown))} "
                         f"(known: [view], [[sheet]])")
    view = doc.get("view", {})
    if not isinstance(view, dict):
        raise ValueError(f"{where}: view must be a table ([view])")
    unknown = set(view) - VIEW_KEYS
    if unknown:
        raise ValueError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(sorted(unknown))} in "
                         f"[view] (known: {', '.join(sorted(VIEW_KEYS))})")
    frame = view.get("frame", "world")
    if not isinstance(frame, str) or not SHEET_NAME.match(frame):
        raise ValueError(f"{where}: [view] frame {frame!r} must be a frame name: 1-64 of A-Z a-z 0-9 _ . -")
    port = view.get("port")
    if port is not None and (not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535):
        raise ValueError(f"{where}: [view] port {port!r} must be a TCP port, 0..65535")
    rate = view.get("rate")
    if rate is not None and (not isinstance(rate, (int, float)) or isinstance(rate, bool) or not 0 < rate <= 1000):
        raise ValueError(f"{where}: [view] rate {rate!r} must be in (0, 1000] per second")
    endpoint = view.get("endpoint")
    if endpoint is not None and (not isinstance(endpoint, str) or not LOCATOR.match(endpoint)):
        raise ValueError(f"{where}: [view] endpoint {endpoint!r} must be a Zenoh locator such as tcp/127.0.0.1:7447")
    sheets = doc.get("sheet")
    if not isinstance(sheets, list) or not sheets or not all(isinstance(s, dict) for s in sheets):
        raise ValueError(f"{where}: no sheet: give one [[sheet]] table per sheet (name, translation, rotation)")
    if len(sheets) > MAX_SHEETS:
        raise ValueError(f"{where}: {len(sheets)} sheets, more than one view draws ({MAX_SHEETS})")
    out: list[SheetPose] = []
    for k, s in enumerate(sheets, 1):
        here = f"{where}: sheet {k}" + (f" ({s['name']!r})" if isinstance(s.get("name"), str) else "")
        unknown = set(s) - SHEET_KEYS
        if unknown:
            raise ValueError(f"{here}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(SHEET_KEYS))})")
        name = s.get("name")
        if not isinstance(name, str) or not SHEET_NAME.match(name):
            raise ValueError(f"{here}: name {name!r} must be a sheet name (its host's --sheet-name): 1-64 of "
                             f"A-Z a-z 0-9 _ . -")
        if name == frame:
            raise ValueError(f"{here}: a sheet cannot be named as the fixed frame {frame!r}")
        if name in {p.name for p in out}:
            raise ValueError(f"{here}: sheet {name!r} is given twice")
        if "translation" not in s:
            raise ValueError(f"{here}: no translation (metres, [x, y, z])")
        t = _numbers(s["translation"], 3, f"{here}: translation (metres)")
        if max(abs(v) for v in t) > MAX_TRANSLATION_M:
            raise ValueError(f"{here}: translation {list(t)} is more than {MAX_TRANSLATION_M:g} m from the fixed frame")
        if ("rotation" in s) == ("rpy_deg" in s):
            raise ValueError(f"{here}: give one of rotation (quaternion [x, y, z, w]) or rpy_deg ([roll, pitch, "
                             f"yaw] degrees)")
        if "rotation" in s:
            q = _numbers(s["rotation"], 4, f"{here}: rotation (quaternion x, y, z, w)")
            norm = math.sqrt(sum(v * v for v in q))
            if abs(norm - 1.0) > QUATERNION_TOLERANCE:
                raise ValueError(f"{here}: rotation {list(q)} is not a unit quaternion (norm {norm:.4g}); give x, y, "
                                 f"z, w of norm 1, or rpy_deg")
            q = tuple(v / norm for v in q)
        else:
            r, p, y = _numbers(s["rpy_deg"], 3, f"{here}: rpy_deg (degrees)")
            q = quaternion_from_rpy(math.radians(r), math.radians(p), math.radians(y))
        out.append(SheetPose(name, t, q))
    return Robot(tuple(out), frame, port, None if rate is None else float(rate), endpoint)


def load_robot(path) -> Robot:
    """Read and check a robot TOML file; ValueError (one line) for a missing file, one that is not a
    regular file or larger than `MAX_CONFIG_BYTES`, bad or too deeply nested TOML, or bad values."""
    p = Path(path)
    try:  # a regular file of a config's size: not a FIFO, not /dev/zero
        text = read_file(p, MAX_CONFIG_BYTES, "a robot config").decode("utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: no such file (a robot config: docs/distribution.md has an example)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read it: {exc}") from None
    return parse_robot(loads_toml(text, str(p)), str(p))  # nesting bounded
