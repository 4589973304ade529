"""Files that may come from anyone (a layout, a calibration, a robot config, a recording someone
sent): opened only if they are regular files, read only up to a size the format can need, parsed
with bounded nesting. Every refusal is a ValueError whose one line names the file and the reason.

Standard library only: the layout reader (`protocol.layout`) and the science's calibration reader
use it as well as the host.

>>> loads_json(b'{"a": [1, 2]}', "x.json")
{'a': [1, 2]}
>>> loads_json(b"[" * 100 + b"]" * 100, "deep.json")
Traceback (most recent call last):
...
ValueError: deep.json: nested 100 levels deep, more than 32
"""

from __future__ import annotations

import json
import os
import stat

__all__ = ["open_regular", "read_file", "loads_json", "loads_toml", "depth", "MAX_DEPTH", "MAX_LINKS"]

#: nesting a capsheet JSON or TOML document never needs more than (a calibration: 4)
MAX_DEPTH = 32
#: links a sheet has at most: assigned node ids are 1..0x7FFF (docs/protocol.md §3,
#: `protocol.messages.NODE_MAX_ASSIGNED`; ``--lattice``'s limit). A file declaring more is refused
#: before anything is sized by it.
MAX_LINKS = 0x7FFF


def open_regular(path, what: str = "a file"):
    """``path`` opened for binary reading if it is a regular file; ValueError otherwise (a FIFO is
    opened without blocking and refused, a device such as ``/dev/zero`` or a folder is refused
    before anything is read). OSError as `open` raises it (missing, no permission)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # OSError: missing, no permission
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode)
                    or stat.S_ISBLK(st.st_mode) else "a folder" if stat.S_ISDIR(st.st_mode) else "not a file")
            raise ValueError(f"{path}: {kind}, not a regular file: need {what}")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        f = os.fdopen(fd, "rb")
        f.raw.name = os.fspath(path)  # as open() names it (messages say which file)
        return f
    except BaseException:
        os.close(fd)
        raise


def read_file(path, max_bytes: int, what: str = "a file") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (`open_regular`); ValueError naming the
    size otherwise (OSError when it cannot be opened). Never reads (nor allocates for) more than
    ``max_bytes + 1`` bytes."""
    with open_regular(path, what) as f:
        size = os.fstat(f.fileno()).st_size
        if size > max_bytes:
            raise ValueError(f"{path}: {size:,} bytes, more than {what} can need ({max_bytes:,})")
        data = f.read(size + 1)  # what it holds (a read of n bytes allocates n at once), and whether it grew
        if len(data) > size:
            data += f.read(max_bytes + 1 - len(data))
    if len(data) > max_bytes:  # it grew while being read
        raise ValueError(f"{path}: more than {max_bytes:,} bytes, more than {what} can need")
    return data


def depth(doc) -> int:
    """How deeply lists and dicts nest in ``doc`` (a scalar: 0), without recursion."""
    best, stack = 0, [(doc, 1)]
    while stack:
        obj, d = stack.pop()
        if isinstance(obj, dict):
            obj = list(obj.values())
        elif not isinstance(obj, list):
            continue
        best = max(best, d)
        stack.extend((v, d + 1) for v in obj if isinstance(v, (dict, list)))
    return best


def loads_json(data, where: str, max_depth: int = MAX_DEPTH):
    """JSON text (str or UTF-8 bytes) -> the document; ValueError naming ``where`` for text that is
    not JSON or nests deeper than ``max_depth``."""
    try:
        doc = json.loads(data)
    except RecursionError:
        raise ValueError(f"{where}: nested too deep to read") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    except (ValueError, UnicodeDecodeError) as exc:  # not UTF-8, an integer of too many digits
        raise ValueError(f"{where}: not valid JSON ({str(exc).splitlines()[0][:80]})") from None
    d = depth(doc)
    if d > max_depth:
        raise ValueError(f"{where}: nested {d} levels deep, more than {max_depth}")
    return doc


def loads_toml(text: str, where: str, max_depth: int = MAX_DEPTH) -> dict:
    """TOML text -> the document; ValueError naming ``where`` for text that is not TOML or nests
    deeper than ``max_depth``."""
    import tomllib

    try:
        doc = tomllib.loads(text)
    except RecursionError:
        raise ValueError(f"{where}: nested too deep to read") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not TOML: {exc}") from None
    d = depth(doc)
    if d > max_depth:
        raise ValueError(f"{where}: nested {d} levels deep, more than {max_depth}")
    return doc
