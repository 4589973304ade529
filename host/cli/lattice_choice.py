"""The lattice of a sheet nobody named: ``capsheet host`` without ``--lattice`` (and without a layout
that names one) asks the sheet first, then decides here — sans I/O, from what answered.

The rule (docs/host.md, "Without --lattice"):

* A **table** of the sheet's links decides when exactly one lattice has that many links, or
  exactly one of those has sides within 2:1 (112 links: 8x8, but also 2x38, 3x23, 5x13 and
  their transposes, which the line names with how to choose them): the gateway nodes' GATEWAY_INFO runs
  (docs/protocol.md §4.16) when they cover links ``0..N-1`` without a gap, else a layout file's
  links (``0..max``). The gateways and the layout say what the sheet *is*; a chip that is dead or
  slow to answer does not change them.
* The **count of chips** that answered never decides alone: one silent chip turns 60 (6x6) into 59,
  and 59 links fit 4x9 exactly — a silent guess would be a wrong lattice, not a missing link. So it
  is said, with the lattices that fit it (and those of a usual shape, sides within 2:1, that fit
  one or two chips more), and the host stops: exit 2, one line.
* A table with more than one lattice (``RxC`` and ``CxR`` have the same links) is said and refused
  the same way.

Lattices are joints ``ROWSxCOLS``, each at least 2, with ``(R-1)C + R(C-1)`` links (docs/design.md §3).
"""

from __future__ import annotations

__all__ = ["lattices_with", "links_of", "table_from_gateways", "choose"]


def links_of(rows: int, cols: int) -> int:
    """
    >>> links_of(6, 6), links_of(64, 64), links_of(14, 14)
    (60, 8064, 364)
    """
    return (rows - 1) * cols + rows * (cols - 1)


def lattices_with(n_links: int, max_side: int = 4096) -> list[tuple[int, int]]:
    """Every lattice ``(rows, cols)`` with exactly ``n_links`` links, rows ascending.

    ``2RC - R - C = n`` gives ``C = (n + R) / (2R - 1)``.

    >>> lattices_with(60), lattices_with(38), lattices_with(59), lattices_with(8064)
    ([(6, 6)], [(4, 6), (6, 4)], [(4, 9), (9, 4)], [(64, 64)])
    >>> lattices_with(2), lattices_with(4), lattices_with(0)
    ([], [(2, 2)], [])
    """
    out = []
    for r in range(2, max_side + 1):
        c, rem = divmod(n_links + r, 2 * r - 1)
        if c < 2:
            break
        if rem == 0 and links_of(r, c) == n_links:
            out.append((r, c))
    return out


def table_from_gateways(runs) -> int | None:
    """The links a set of gateway runs ``(first_link, link_count)`` covers, when they cover
    ``0..N-1`` without a gap or an overlap; else None.

    >>> table_from_gateways([(0, 1613), (1613, 1613), (3226, 1613), (4839, 1613), (6452, 1612)])
    8064
    >>> table_from_gateways([(0, 10), (12, 10)]) is None, table_from_gateways([]) is None
    (True, True)
    """
    runs = sorted(set((int(a), int(n)) for a, n in runs if n > 0))
    if not runs:
        return None
    end = 0
    for a, n in runs:
        if a != end:
            return None
        end = a + n
    return end


def _usual(r: int, c: int) -> bool:
    """A sheet's usual shape: sides within 2:1 (a strip of 2 x 38 joints is a sheet too, but one
    that is said, never assumed)."""
    return max(r, c) <= 2 * min(r, c)


def _names(lats) -> str:
    return ", ".join(f"{r}x{c}" for r, c in lats)


def choose(chips: int | None, gateway_runs=(), layout_links: int | None = None) -> tuple[tuple[int, int] | None, str]:
    """``((rows, cols), why)`` when the answers decide the lattice; ``(None, why)`` when they do not
    (``why`` is then the one line the host stops with). ``chips``: how many chips answered (None:
    the sheet was not asked, a layout decides);
    ``gateway_runs``: ``(first_link, link_count)`` of every GATEWAY_INFO heard; ``layout_links``: a
    layout file's highest link + 1.

    >>> choose(60)[0] is None
    True
    >>> print(choose(60)[1])
    60 chips answered and no gateway or layout says how many links the sheet has; lattices with 60 links: 6x6 (with 1-2 chips silent: none); give --lattice ROWSxCOLS
    >>> print(choose(59)[1].split("; ")[1])
    lattices with 59 links: 4x9, 9x4 (with 1-2 chips silent: 6x6)
    >>> choose(8000, [(0, 4032), (4032, 4032)])
    ((64, 64), 'the gateways serve links 0-8063 (8064 links): 64x64 is the one lattice with that many; using it (8000 chips answered)')
    >>> choose(38, [(0, 38)])[0] is None  # 4x6 or 6x4: the gateway does not say which
    True
    >>> print(choose(None, layout_links=112)[1])
    the layout names links 0-111 (112 links): 8x8 is the one lattice with that many and sides within 2:1; using it (give --lattice for 2x38, 3x23, 5x13, 13x5, 23x3, 38x2, which have as many)
    """
    heard = "" if chips is None else f" ({chips} chips answered)"
    table, source = table_from_gateways(gateway_runs), "the gateways serve"
    if table is None and layout_links:
        table, source = layout_links, "the layout names"
    if table is not None:
        fits = lattices_with(table)
        said = f"{source} links 0-{table - 1} ({table} links)"
        if len(fits) == 1:
            r, c = fits[0]
            return fits[0], f"{said}: {r}x{c} is the one lattice with that many; using it{heard}"
        usual = [(r, c) for r, c in fits if _usual(r, c)]
        if len(usual) == 1:
            r, c = usual[0]
            others = _names([f for f in fits if f != usual[0]])
            return usual[0], (f"{said}: {r}x{c} is the one lattice with that many and sides within 2:1; "
                              f"using it{heard} (give --lattice for {others}, which have as many)")
        return None, (f"{said}, which fits " + (f"the lattices {_names(fits)}" if fits else "no lattice")
                      + f"{heard}; give --lattice ROWSxCOLS")
    fits = lattices_with(chips)
    # one or two chips silent: the lattices of a sheet's usual shape only (sides within 2:1), not
    # every strip that happens to have the count
    near = [(r, c) for k in (1, 2) for r, c in lattices_with(chips + k) if _usual(r, c)]
    return None, (f"{chips} chips answered and no gateway or layout says how many links the sheet has; "
                  f"lattices with {chips} links: {_names(fits) or 'none'} (with 1-2 chips silent: "
                  f"{_names(near) or 'none'}); give --lattice ROWSxCOLS")
