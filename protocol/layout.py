"""The layout file: which chip (64-bit uid) sits on which link. One format, read and written by the
host (`host.session.core.Host`) and the virtual sheet (`virtual_sheet.sheet.VirtualSheet.write_layout`).

Sans-I/O: `parse_layout` / `format_layout` work on text; `load_layout` / `save_layout` are the thin
file wrappers. The format is chosen by the file's extension: ``.json`` is JSON, anything else CSV.

**The uid rule** (one rule, both formats): a uid is written in **hexadecimal**, with or without a
``0x`` prefix, 1..16 hex digits, case-insensitive (``0x0123456789ABCDEF``, ``123456789abcdef``).
Decimal uids are not accepted (``"10"`` is 0x10). Links are decimal integers ``>= 0``.

* CSV: an optional header line ``uid,link``, then one chip per line; ``#`` starts a comment::

      uid,link
      0x0123456789ABCDEF,0
      0x0123456789ABCDF0,1

* JSON: the lattice may be given (``rows``/``cols``, joints), and a host takes it from there::

      {"format": "capsheet-layout", "version": 1, "rows": 14, "cols": 14,
       "chips": [{"uid": "0x0123456789ABCDEF", "link": 0}, ...]}

Every error is a `LayoutError` (a `ValueError`) naming the file, the line or chip index, and the value.

>>> doc = parse_layout("uid,link\\n0xA,0\\nb,1\\n", "sheet.csv")
>>> doc.links == {10: 0, 11: 1}, doc.rows
(True, None)
>>> parse_layout('{"rows": 2, "cols": 3, "chips": [{"uid": "0x0A", "link": 4}]}', "s.json").lattice
'2x3'
>>> print(format_layout({10: 0}, "s.csv"), end="")
uid,link
0x000000000000000A,0
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from protocol.files import MAX_LINKS, loads_json, read_file

__all__ = ["LayoutError", "LayoutDoc", "parse_uid", "parse_layout", "format_layout", "load_layout",
           "save_layout", "FORMAT_NAME", "FORMAT_VERSION", "MAX_LAYOUT_BYTES"]

FORMAT_NAME = "capsheet-layout"
FORMAT_VERSION = 1
#: a layout file larger than this is refused unread: `MAX_LINKS` chips of ~60 bytes each, with room
MAX_LAYOUT_BYTES = 8 << 20
_HEX_UID = re.compile(r"^(0[xX])?([0-9a-fA-F]{1,16})$")


class LayoutError(ValueError):
    """A layout file (or text) that does not follow the format; the message names where."""


def parse_uid(text, where: str = "uid") -> int:
    """A uid from its text: hex, ``0x`` optional, 1..16 digits (module docstring).

    >>> hex(parse_uid("0x0123456789ABCDEF")), parse_uid("ff")
    ('0x123456789abcdef', 255)
    """
    if not isinstance(text, str):
        raise LayoutError(f"{where}: uid must be a hex string like '0x0123456789ABCDEF', got {text!r}")
    m = _HEX_UID.match(text.strip())
    if m is None:
        raise LayoutError(f"{where}: invalid uid {text!r} (need 1..16 hex digits, '0x' optional)")
    return int(m.group(2), 16)


def _parse_link(value, where: str) -> int:
    if isinstance(value, bool):
        raise LayoutError(f"{where}: invalid link {value!r} (need a decimal integer >= 0)")
    if isinstance(value, int):
        link = value
    elif isinstance(value, str) and value.strip().isdigit():
        link = int(value.strip())
    else:
        raise LayoutError(f"{where}: invalid link {value!r} (need a decimal integer >= 0)")
    if link < 0:
        raise LayoutError(f"{where}: invalid link {value!r} (need >= 0)")
    if link >= MAX_LINKS:
        raise LayoutError(f"{where}: invalid link {value!r} (a sheet has at most {MAX_LINKS:,} links: 0..{MAX_LINKS - 1})")
    return link


@dataclass(frozen=True, slots=True)
class LayoutDoc:
    """A parsed layout: ``links`` uid -> link, and the lattice (joints) when the file gives one."""

    links: dict = field(default_factory=dict)
    rows: int | None = None
    cols: int | None = None

    def __post_init__(self) -> None:
        if (self.rows is None) != (self.cols is None):
            raise LayoutError(f"Invalid lattice: rows={self.rows!r}, cols={self.cols!r} (give both or neither)")
        if self.rows is not None:
            n = self.rows * (self.cols - 1) + self.cols * (self.rows - 1)
            if n > MAX_LINKS:
                raise LayoutError(f"Invalid lattice: {self.rows}x{self.cols} has {n:,} links, more than a sheet's "
                                  f"{MAX_LINKS:,} (node ids 1..0x7FFF)")
            big = [link for link in self.links.values() if isinstance(link, int) and link >= n]
            if big:
                raise LayoutError(f"Invalid link {max(big)}: the {self.rows}x{self.cols} lattice has links 0..{n - 1}")
        if len(self.links) > MAX_LINKS:
            raise LayoutError(f"Invalid layout: {len(self.links):,} chips, more than a sheet's {MAX_LINKS:,}")
        seen: dict[int, int] = {}
        for uid, link in self.links.items():
            if not (isinstance(uid, int) and 0 <= uid < (1 << 64)):
                raise LayoutError(f"Invalid uid: {uid!r} (need 64 bits)")
            if not isinstance(link, int) or isinstance(link, bool) or link < 0:
                raise LayoutError(f"Invalid link for uid 0x{uid:016X}: {link!r}")
            if link in seen:
                raise LayoutError(f"Link {link} is given to two chips: 0x{seen[link]:016X} and 0x{uid:016X}")
            seen[link] = uid

    @property
    def lattice(self) -> str | None:
        """``"ROWSxCOLS"`` or None."""
        return None if self.rows is None else f"{self.rows}x{self.cols}"


def _is_json(name) -> bool:
    return str(name).lower().endswith(".json")


def parse_layout(text: str, name: str = "layout.csv") -> LayoutDoc:
    """Parse layout ``text``; ``name`` (a file name) chooses the format and is named in errors."""
    if not isinstance(text, str):
        raise LayoutError(f"{name}: not text")
    if _is_json(name):
        return _parse_json(text, name)
    return _parse_csv(text, name)


def _parse_json(text: str, name: str) -> LayoutDoc:
    try:
        doc = loads_json(text, name)  # nesting bounded
    except ValueError as exc:
        raise LayoutError(str(exc)) from None
    if not isinstance(doc, dict):
        raise LayoutError(f"{name}: expected a JSON object with 'chips', got {type(doc).__name__}")
    if "format" in doc and doc["format"] != FORMAT_NAME:
        raise LayoutError(f"{name}: format {doc['format']!r} is not {FORMAT_NAME!r}")
    if "version" in doc and doc["version"] != FORMAT_VERSION:
        raise LayoutError(f"{name}: version {doc['version']!r} not supported (need {FORMAT_VERSION})")
    rows = cols = None
    if "rows" in doc or "cols" in doc:
        rows, cols = doc.get("rows"), doc.get("cols")
        for key, v in (("rows", rows), ("cols", cols)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 2:
                raise LayoutError(f"{name}: invalid {key} {v!r} (need an integer >= 2; lattice joints)")
    chips = doc.get("chips")
    if not isinstance(chips, list):
        raise LayoutError(f"{name}: 'chips' must be a list of {{'uid': '0x..', 'link': N}}, got {chips!r:.60}")
    links: dict[int, int] = {}
    for i, chip in enumerate(chips):
        where = f"{name}: chips[{i}]"
        if not isinstance(chip, dict) or "uid" not in chip or "link" not in chip:
            raise LayoutError(f"{where}: expected {{'uid': '0x..', 'link': N}}, got {chip!r:.60}")
        uid, link = parse_uid(chip["uid"], where), _parse_link(chip["link"], where)
        if uid in links:
            raise LayoutError(f"{where}: uid 0x{uid:016X} appears twice")
        links[uid] = link
    return _doc(links, rows, cols, name)


def _parse_csv(text: str, name: str) -> LayoutDoc:
    if "\x00" in text:
        raise LayoutError(f"{name}: binary data, not a 'uid,link' CSV file")
    links: dict[int, int] = {}
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    for lineno, row in enumerate(csv.reader(lines), start=1):
        if not row or not "".join(row).strip():
            continue
        if row[0].strip().lower() == "uid":
            continue
        where = f"{name}:{lineno}"
        if len(row) != 2:
            raise LayoutError(f"{where}: expected 'uid,link' (hex uid, decimal link), got {','.join(row)!r}")
        uid, link = parse_uid(row[0], where), _parse_link(row[1], where)
        if uid in links:
            raise LayoutError(f"{where}: uid 0x{uid:016X} appears twice")
        links[uid] = link
    return _doc(links, None, None, name)


def _doc(links, rows, cols, name) -> LayoutDoc:
    try:
        return LayoutDoc(links, rows, cols)
    except LayoutError as exc:
        raise LayoutError(f"{name}: {exc}") from None


def format_layout(links: dict, name: str = "layout.csv", rows: int | None = None, cols: int | None = None) -> str:
    """The text of a layout file (format by ``name``'s extension), chips in link order."""
    doc = LayoutDoc(dict(links), rows, cols)
    items = sorted(doc.links.items(), key=lambda kv: kv[1])
    if _is_json(name):
        out: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION}
        if rows is not None:
            out.update(rows=rows, cols=cols)
        out["chips"] = [{"uid": f"0x{u:016X}", "link": k} for u, k in items]
        return json.dumps(out, indent=1) + "\n"
    return "uid,link\n" + "".join(f"0x{u:016X},{k}\n" for u, k in items)


def load_layout(path) -> LayoutDoc:
    """Read a layout file. Raises `LayoutError` (missing, unreadable, not a regular file, larger than
    `MAX_LAYOUT_BYTES`, binary, malformed, a lattice or a link beyond a sheet's `MAX_LINKS`)."""
    path = Path(path)
    try:  # a regular file of a layout's size: not a FIFO, not /dev/zero
        data = read_file(path, MAX_LAYOUT_BYTES, "a layout file")
    except ValueError as exc:
        raise LayoutError(str(exc)) from None
    except OSError as exc:
        raise LayoutError(f"{path}: cannot read layout file ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise LayoutError(f"{path}: binary data, not a layout file (CSV 'uid,link' or JSON)") from None
    return parse_layout(text, str(path))


def save_layout(path, links: dict, rows: int | None = None, cols: int | None = None) -> Path:
    """Write a layout file (format by extension); returns the path."""
    path = Path(path)
    path.write_text(format_layout(links, str(path), rows, cols))
    return path
