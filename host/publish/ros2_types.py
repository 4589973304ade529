"""ROS 2 message types without ROS: the message definitions capsheet publishes (the standard ones it
uses, as ROS 2 Jazzy's common_interfaces define them, and capsheet's own ``msgs/capsheet_msgs``),
their REP-2011 type hashes (`rihs01`), their DDS names, and CDR little-endian encoding (`Cdr`). What
`host.publish.ros2` lays out on Zenoh as rmw_zenoh does is encoded with these."""

from __future__ import annotations

import hashlib
import json
import re
import struct
from pathlib import Path

import numpy as np

__all__ = ["MSGS_DIR", "MsgType", "TypeRegistry", "registry", "rihs01", "dds_type_name", "CDR_LE_HEADER", "Cdr",
           "STANDARD", "FIELD_TYPE_ID"]

#: the capsheet_msgs package in the repository (a ROS 2 package: colcon builds it)
MSGS_DIR = Path(__file__).resolve().parents[2] / "msgs"

# -- message definitions -----------------------------------------------------------------------------
#: the standard definitions this module uses, as in ROS 2 Jazzy's common_interfaces (comments and
#: default values left out: neither enters the type hash nor the CDR)
STANDARD = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/String": "string data\n",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "sensor_msgs/msg/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n"
        "uint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n"),
    "sensor_msgs/msg/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n"
        "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"),
    "sensor_msgs/msg/MagneticField": (
        "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\nfloat64[9] magnetic_field_covariance\n"),
    "visualization_msgs/msg/UVCoordinate": "float32 u\nfloat32 v\n",
    "visualization_msgs/msg/MeshFile": "string filename\nuint8[] data\n",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\nint32 LINE_LIST=5\n"
        "int32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\nint32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\n"
        "int32 TRIANGLE_LIST=11\nint32 ARROW_STRIP=12\nint32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\n"
        "int32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\n"
        "geometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\n"
        "bool frame_locked\ngeometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\nstring texture_resource\n"
        "sensor_msgs/CompressedImage texture\nUVCoordinate[] uv_coordinates\nstring text\nstring mesh_resource\n"
        "MeshFile mesh_file\nbool mesh_use_embedded_materials\n"),
    "diagnostic_msgs/msg/KeyValue": "string key\nstring value\n",
    "diagnostic_msgs/msg/DiagnosticStatus": (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n"
        "byte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n"),
    "diagnostic_msgs/msg/DiagnosticArray": "std_msgs/Header header\nDiagnosticStatus[] status\n",
}

#: type_description_interfaces/msg/FieldType ids (REP-2011)
FIELD_TYPE_ID = {"nested": 1, "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7,
                 "int64": 8, "uint64": 9, "float32": 10, "float64": 11, "char": 3, "bool": 15, "byte": 16,
                 "string": 17, "wstring": 18}
_BOUNDED_STRING = {"string": 21, "wstring": 22}
_ARRAY, _BOUNDED_SEQ, _SEQ = 48, 96, 144
_FIELD = re.compile(r"^(?P<type>[A-Za-z][\w/]*)(?:<=(?P<sbound>\d+))?(?P<arr>\[(?:<=)?\d*\])?$")


class MsgType:
    """One parsed ``.msg``: ``name`` (``pkg/msg/Type``), ``fields`` [(name, base, array, capacity,
    string_capacity)] with ``array`` one of ``None``, ``"fixed"``, ``"bounded"``, ``"seq"`` and
    ``base`` a primitive or a full nested type name, and the definition ``text``."""

    def __init__(self, name: str, text: str) -> None:
        self.name, self.text = name, text
        pkg = name.split("/")[0]
        self.fields: list[tuple[str, str, str | None, int, int]] = []
        for raw in text.splitlines():
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split(None, 2)
            if len(parts) < 2:
                raise ValueError(f"{name}: cannot read {raw!r}")
            typ, fname = parts[0], parts[1]
            if "=" in fname or (len(parts) > 2 and parts[2].startswith("=")):
                continue  # a constant: not in the type description, not on the wire
            m = _FIELD.match(typ)
            if not m:
                raise ValueError(f"{name}: unsupported field type {typ!r}")
            base, arr = m["type"], m["arr"]
            array, capacity = None, 0
            if arr:
                inner = arr[1:-1]
                if inner == "":
                    array = "seq"
                elif inner.startswith("<="):
                    array, capacity = "bounded", int(inner[2:])
                else:
                    array, capacity = "fixed", int(inner)
            if base not in FIELD_TYPE_ID or base == "nested":
                if base == "Header":
                    base = "std_msgs/msg/Header"
                elif "/" in base:
                    p, _, t = base.rpartition("/")
                    base = f"{p.split('/')[0]}/msg/{t}"
                else:
                    base = f"{pkg}/msg/{base}"
            self.fields.append((fname, base, array, capacity, int(m["sbound"] or 0)))

    @property
    def nested(self) -> list[str]:
        return [b for _, b, *_ in self.fields if b not in FIELD_TYPE_ID]


class TypeRegistry:
    """The message types known: `STANDARD` and the ``.msg`` files of `MSGS_DIR`'s packages."""

    def __init__(self) -> None:
        self.types: dict[str, MsgType] = {}
        self._hash: dict[str, str] = {}
        for n, t in STANDARD.items():
            self.add(n, t)
        for f in sorted(MSGS_DIR.glob("*/msg/*.msg")):
            self.add(f"{f.parent.parent.name}/msg/{f.stem}", f.read_text())

    def add(self, name: str, text: str) -> MsgType:
        """Add (or replace) a type from its ``.msg`` text; hashes are computed anew."""
        self.types[name] = MsgType(name, text)
        self._hash.clear()
        return self.types[name]

    def closure(self, name: str) -> list[str]:
        """Every type ``name`` refers to, directly or not (``name`` not included), in first-use order."""
        seen: list[str] = []
        todo = list(self.types[name].nested)
        while todo:
            t = todo.pop(0)
            if t in seen or t == name:
                continue
            if t not in self.types:
                raise ValueError(f"{name} refers to {t}, not known")
            seen.append(t)
            todo.extend(self.types[t].nested)
        return seen

    def _description(self, name: str) -> dict:
        fields = []
        for fname, base, array, capacity, scap in self.types[name].fields:
            if base in FIELD_TYPE_ID:
                tid = _BOUNDED_STRING[base] if scap and base in _BOUNDED_STRING else FIELD_TYPE_ID[base]
                nested = ""
            else:
                tid, nested = FIELD_TYPE_ID["nested"], base
            tid += {None: 0, "fixed": _ARRAY, "bounded": _BOUNDED_SEQ, "seq": _SEQ}[array]
            fields.append({"name": fname, "type": {"type_id": tid, "capacity": capacity, "string_capacity": scap,
                                                   "nested_type_name": nested}})
        if not fields:  # REP-2011: an empty message is described with one uint8 member
            fields = [{"name": "structure_needs_at_least_one_member",
                       "type": {"type_id": 3, "capacity": 0, "string_capacity": 0, "nested_type_name": ""}}]
        return {"type_name": name, "fields": fields}

    def rihs01(self, name: str) -> str:
        """REP-2011 type hash, ``RIHS01_`` + SHA-256 of the type description's JSON (rosidl's
        rosidl_generator_type_description: the description and every referenced type's, sorted
        by name, default values left out, ``", "`` / ``": "`` separators)."""
        if name not in self._hash:
            doc = {"type_description": self._description(name),
                   "referenced_type_descriptions": [self._description(t) for t in sorted(self.closure(name))]}
            text = json.dumps(doc, ensure_ascii=True, allow_nan=False, separators=(", ", ": "), sort_keys=False)
            self._hash[name] = "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()
        return self._hash[name]

    def msgdef(self, name: str) -> str:
        """The ROS 2 concatenated ``.msg`` definition (MCAP schema encoding ``ros2msg``): the type's
        own text, then ``====...`` and ``MSG: pkg/Type`` before each referenced type's."""
        parts = [self.types[name].text.rstrip("\n") + "\n"]
        for t in self.closure(name):
            pkg, _, typ = t.split("/")
            parts.append("=" * 80 + f"\nMSG: {pkg}/{typ}\n" + self.types[t].text.rstrip("\n") + "\n")
        return "".join(parts)


_REGISTRY: TypeRegistry | None = None


def registry() -> TypeRegistry:
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = TypeRegistry()
    return _REGISTRY


def rihs01(name: str) -> str:
    return registry().rihs01(name)


def dds_type_name(name: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_`` (the CDR type
    name rmw_zenoh puts in key expressions)."""
    pkg, sub, typ = name.split("/")
    return f"{pkg}::{sub}::dds_::{typ}_"


# -- CDR -------------------------------------------------------------------------------------------
#: CDR, little-endian (encapsulation kind 0x0001), options 0
CDR_LE_HEADER = b"\x00\x01\x00\x00"


class Cdr:
    """A little-endian CDR (XCDR1, as ROS 2 uses it) writer: alignment of each primitive to its
    size (8 at most), counted from after the 4-byte encapsulation header."""

    def __init__(self) -> None:
        self.buf = bytearray(CDR_LE_HEADER)

    def align(self, n: int) -> None:
        pad = (-(len(self.buf) - 4)) % n
        if pad:
            self.buf += b"\x00" * pad

    def u8(self, v: int) -> None:
        self.buf.append(int(v) & 0xFF)

    def bool(self, v) -> None:
        self.buf.append(1 if v else 0)

    def i32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<i", int(v))

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<I", int(v))

    def u16(self, v: int) -> None:
        self.align(2)
        self.buf += struct.pack("<H", int(v))

    def u64(self, v: int) -> None:
        self.align(8)
        self.buf += struct.pack("<Q", int(v) & (2**64 - 1))

    def f64(self, *vs: float) -> None:
        self.align(8)
        self.buf += struct.pack(f"<{len(vs)}d", *vs)

    def f32(self, *vs: float) -> None:
        self.align(4)
        self.buf += struct.pack(f"<{len(vs)}f", *vs)

    def string(self, s: str) -> None:
        b = s.encode()
        self.u32(len(b) + 1)
        self.buf += b + b"\x00"

    def seq(self, arr: np.ndarray, dtype: str, count: int | None = None) -> None:
        """A sequence of primitives: its length (elements; ``count`` when the array holds several
        values per element, e.g. a struct of three float64), then the values, aligned to their size."""
        a = np.ascontiguousarray(arr, dtype=dtype)
        self.u32(a.size if count is None else count)
        if a.size:
            self.align(a.dtype.itemsize)
            self.buf += a.tobytes()

    def header(self, stamp_ns: int, frame_id: str) -> None:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        self.i32(sec)
        self.u32(nsec)
        self.string(frame_id)

    def bytes(self) -> bytes:
        return bytes(self.buf)
