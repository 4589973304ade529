"""The chip registry: what the host knows of each chip (`ChipRecord`), which chip sits on which
link (`Layout`), and the node id a link's chip gets (`node_for_link`).

Node ids: the chip on link ``k`` gets node id ``k + 1`` (1..0x7FFF), so node ids are dense, stable
across runs and the aggregator's lookup is a fixed table.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from protocol.constants import nominal_sensitivity
from protocol.lattice import Lattice
from protocol.layout import LayoutDoc, load_layout, save_layout
from protocol.messages import NODE_MAX_ASSIGNED, Info, Status

__all__ = ["Layout", "ChipRecord", "node_for_link"]

log = logging.getLogger("capsheet.host")


def node_for_link(link: int) -> int:
    """Node id the host assigns to the chip on ``link``: ``link + 1``."""
    if not 0 <= link < NODE_MAX_ASSIGNED:
        raise ValueError(f"Invalid link {link}: node ids cover links 0..{NODE_MAX_ASSIGNED - 1}")
    return link + 1


@dataclass(frozen=True)
class Layout:
    """Which chip (64-bit uid) sits on which link (lattice address, docs/design.md link order).

    The file format (CSV or JSON, uids in hex) is `protocol.layout`'s, shared with the virtual
    sheet; `load` and `save` are its thin wrappers. ``lattice`` is ``"ROWSxCOLS"`` when the file
    gives one (JSON), else None.
    """

    links: dict  # uid -> link
    lattice: str | None = None
    is_auto: bool = False  #: made by `Layout.auto`: positions are arbitrary

    def __post_init__(self) -> None:
        rows = cols = None
        if self.lattice is not None:
            r, _, c = str(self.lattice).lower().partition("x")
            if not (r.isdigit() and c.isdigit()):
                raise ValueError(f"Invalid lattice: {self.lattice!r} (need 'ROWSxCOLS')")
            rows, cols = int(r), int(c)
        LayoutDoc(dict(self.links), rows, cols)  # validates uids, links, duplicates

    @classmethod
    def load(cls, path) -> "Layout":
        """Read a layout file; raises `protocol.layout.LayoutError` (a ValueError) naming the problem."""
        doc = load_layout(path)
        return cls(dict(doc.links), doc.lattice)

    def save(self, path) -> None:
        rows = cols = None
        if self.lattice:
            r, c = self.lattice.lower().split("x")
            rows, cols = int(r), int(c)
        save_layout(path, self.links, rows, cols)

    @classmethod
    def auto(cls, uids: Sequence[int], lattice: Lattice) -> "Layout":
        """Auto-assign: chips in ascending uid order take links 0, 1, 2, ... The positions are then
        arbitrary (a shape estimate is meaningless until a real layout is given); a warning says so."""
        uids = sorted(set(int(u) for u in uids))
        if len(uids) > lattice.n_links:
            log.warning("auto-assign: %d chips for %d links; the extra chips stay unassigned", len(uids),
                        lattice.n_links)
        log.warning("auto-assign: %d chips placed on links in uid order; positions are arbitrary "
                    "(give a layout file for a meaningful shape)", min(len(uids), lattice.n_links))
        return cls({u: k for k, u in enumerate(uids[:lattice.n_links])}, f"{lattice.rows}x{lattice.cols}", is_auto=True)


@dataclass
class ChipRecord:
    """What the host knows about one chip."""

    uid: int
    node: int  #: the node id it speaks from now (provisional until assigned)
    bus: int  #: index of the transport it was heard on
    info: Info | None = None
    link: int | None = None
    assigned: bool = False
    configured: bool = False
    started: bool = False
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  #: counts (at the configured range)
    sensitivity: np.ndarray = field(default_factory=lambda: np.full(3, nominal_sensitivity()))  #: counts/g
    calibrated: bool = False  #: CAL_DATA read for all three axes
    last_status: Status | None = None
    nacks: list = field(default_factory=list)  #: (command name, reason name), the last `MAX_NACKS` kept
    started_at: float = float("-inf")  #: host time of its START ACK

    MAX_NACKS = 16
