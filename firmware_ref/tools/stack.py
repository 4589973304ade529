"""Static worst-case stack depth from GCC's call-graph files (``-fcallgraph-info=su``, *.ci).

    python3 firmware_ref/tools/stack.py build/size/stack/*.ci --root capsheet_chip_rx_bytes ...

For each root: the deepest call path and its stack (the sum of each function's static frame).
Indirect calls (the HAL callbacks) count as the deepest function given with ``--indirect``
(default: none, 0 bytes); library calls (memcpy/memset) as 0 bytes (reported). No recursion is
assumed (a cycle is an error). Prints one line per root: ``root: N B via a > b > c``.
"""

from __future__ import annotations

import argparse
import re
import sys
from functools import lru_cache


def parse(paths: list[str]):
    size: dict[str, int] = {}
    edges: dict[str, set[str]] = {}
    alias: dict[str, str] = {}
    for p in paths:
        text = open(p).read()
        for title, label in re.findall(r'node: \{ title: "([^"]+)" label: "([^"]*)"', text):
            m = re.search(r"\\n(\d+) bytes \((?:static|dynamic,bounded|dynamic)\)", label)
            name = label.split("\\n", 1)[0]
            if m:
                size[title] = int(m.group(1))
                alias.setdefault(name, title)  # resolve a public name to its definition
        for a, b in re.findall(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"', text):
            edges.setdefault(a, set()).add(b)
    return size, edges, alias


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("files", nargs="+")
    p.add_argument("--root", action="append", required=True)
    p.add_argument("--indirect", action="append", default=[], help="functions an indirect call may reach")
    args = p.parse_args()
    size, edges, alias = parse(args.files)

    def resolve(n: str) -> str:
        return n if n in size else alias.get(n.split(":")[-1], n)

    unknown: set[str] = set()

    @lru_cache(maxsize=None)
    def depth(n: str, stack: tuple = ()) -> tuple[int, tuple]:
        n = resolve(n)
        if n in stack:
            raise SystemExit(f"recursion through {n}")
        own = size.get(n)
        if own is None:
            if n == "__indirect_call":
                best = max((depth(i, stack) for i in args.indirect), default=(0, ()))
                return best[0], ("<HAL>",) + best[1]
            unknown.add(n)
            return 0, (n,)
        best = (0, ())
        for m in edges.get(n, ()):
            best = max(best, depth(m, stack + (n,)))
        return own + best[0], (n.split(":")[-1],) + best[1]

    for r in args.root:
        d, path = depth(r)
        print(f"{r}: {d} B via {' > '.join(path)}")
    if unknown:
        print(f"(counted as 0 B: {', '.join(sorted(unknown))})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
