"""Recording snapshots to a file numpy loads directly (docs/host.md, "Record format").

A recording ``out.cap`` is a plain **.npy file** (NumPy format 1.0) holding a 1-D structured array,
one record per `LatticeSnapshot`, written incrementally: the header is written with room for the
record count and rewritten (same length) at every flush and on close. So::

    import numpy as np
    rec = np.load("out.cap", mmap_mode="r")          # structured array, one row per snapshot
    rec["readings"].shape, rec["valid"].mean()        # (n, n_links, 3) m/s², completeness

Fields: ``counter`` u2, ``timestamp`` f8 (host monotonic s at SYNC), ``wall_time`` f8 (Unix s),
``latency_s`` f4, ``complete`` ?, ``readings`` f4 (n_links, 3) m/s² (NaN where invalid),
``valid`` ? (n_links,), ``status`` u1 (n_links,) (`host.aggregator.LinkFlag` bits).

Beside it, ``out.cap.json`` holds the metadata (lattice rows/cols, rate, layout, transports, the
final statistics). A file cut short by a crash loads with `read_recording`, which counts records
from the file size rather than trusting the header.
"""

from __future__ import annotations

import ast
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .aggregator import LatticeSnapshot

__all__ = ["record_dtype", "RecordWriter", "Recording", "read_recording"]

_MAGIC = b"\x93NUMPY\x01\x00"
_HEADER_LEN = 4096 - 10  # total header 4096 bytes: magic (8) + u16 length (2) + text


def record_dtype(n_links: int) -> np.dtype:
    """The structured dtype of one record for a lattice of ``n_links`` links."""
    return np.dtype([("counter", "<u2"), ("timestamp", "<f8"), ("wall_time", "<f8"), ("latency_s", "<f4"),
                     ("complete", "?"), ("readings", "<f4", (n_links, 3)), ("valid", "?", (n_links,)),
                     ("status", "u1", (n_links,))])


def _header(dtype: np.dtype, count: int) -> bytes:
    text = "{'descr': %r, 'fortran_order': False, 'shape': (%d,), }" % (
        np.lib.format.dtype_to_descr(dtype), count)
    if len(text) + 1 > _HEADER_LEN:
        raise ValueError(f"Record dtype too large for the header ({len(text)} bytes)")
    text = text.ljust(_HEADER_LEN - 1) + "\n"
    return _MAGIC + _HEADER_LEN.to_bytes(2, "little") + text.encode("latin1")


class RecordWriter:
    """Write snapshots to ``path`` (a .npy file) and metadata to ``path + '.json'``.

    Parameters
    ----------
    path : str or Path
    n_links : int
    metadata : dict
        Stored in the sidecar JSON (e.g. ``{"rows": 14, "cols": 14, "rate_hz": 100}``).
    flush_interval_s : float
        The header's record count is brought up to date at least this often.
    """

    def __init__(self, path, n_links: int, metadata: dict | None = None, flush_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.n_links = int(n_links)
        self.dtype = record_dtype(self.n_links)
        self.metadata = dict(metadata or {})
        self.metadata.update({"n_links": self.n_links, "format": "capsheet-record-1 (.npy structured array)",
                              "started": time.time()})
        self.count = 0
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._f = open(self.path, "wb")
        self._f.write(_header(self.dtype, 0))
        self._row = np.zeros(1, dtype=self.dtype)
        self._write_meta()

    def _write_meta(self, extra: dict | None = None) -> None:
        meta = dict(self.metadata)
        meta["count"] = self.count
        if extra:
            meta.update(extra)
        tmp = self.path.with_name(self.path.name + ".json.tmp")
        tmp.write_text(json.dumps(meta, indent=2, default=_jsonable))
        os.replace(tmp, self.path.with_name(self.path.name + ".json"))

    def write(self, snap: LatticeSnapshot) -> None:
        if snap.n_links != self.n_links:
            raise ValueError(f"Expected a snapshot of {self.n_links} links, got {snap.n_links}")
        r = self._row
        r["counter"] = snap.counter
        r["timestamp"] = snap.timestamp
        r["wall_time"] = snap.wall_time
        r["latency_s"] = snap.latency_s
        r["complete"] = snap.complete
        r["readings"][0] = snap.readings
        r["valid"][0] = snap.valid
        r["status"][0] = snap.status
        self._f.write(r.tobytes())
        self.count += 1
        if time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Bring the header's count up to date and push the data to the OS."""
        self._f.flush()
        pos = self._f.tell()
        self._f.seek(0)
        self._f.write(_header(self.dtype, self.count))
        self._f.seek(pos)
        self._f.flush()
        self._last_flush = time.monotonic()

    def close(self, stats: dict | None = None) -> None:
        if self._f.closed:
            return
        self.flush()
        self._f.close()
        self._write_meta({"finished": time.time(), **({"stats": stats} if stats else {})})

    def __enter__(self) -> "RecordWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


@dataclass(frozen=True)
class Recording:
    """A loaded recording: ``data`` (structured array, memory-mapped) and ``metadata`` (dict)."""

    data: np.ndarray
    metadata: dict

    def __len__(self) -> int:
        return int(self.data.shape[0])

    @property
    def readings(self) -> np.ndarray:
        """shape (n, n_links, 3), float32, m/s², sensor frame; NaN where not valid."""
        return self.data["readings"]

    @property
    def valid(self) -> np.ndarray:
        return self.data["valid"]


def read_recording(path) -> Recording:
    """Load a recording, tolerating a file cut short (records are counted from the file size)."""
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(8)
        if magic[:6] != _MAGIC[:6]:
            raise ValueError(f"{str(path)!r} is not a capsheet recording (.npy magic missing)")
        major = magic[6]
        hlen_size = 2 if major == 1 else 4
        hlen = int.from_bytes(f.read(hlen_size), "little")
        header = ast.literal_eval(f.read(hlen).decode("latin1"))
        offset = 8 + hlen_size + hlen
    dtype = np.lib.format.descr_to_dtype(header["descr"])
    n = (path.stat().st_size - offset) // dtype.itemsize
    data = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(n,)) if n else np.zeros(0, dtype)
    meta_path = path.with_name(path.name + ".json")
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    return Recording(data, meta)
