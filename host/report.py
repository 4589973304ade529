"""The run report: what the host reports (`HostEvent`) and how links are named in it (`link_ranges`)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["HostEvent", "link_ranges"]


def link_ranges(links, limit: int = 12) -> str:
    """Links as compact ranges, for one log line per incident; past ``limit`` ranges the rest is
    counted, not listed (a 128x128 sheet's incident stays one readable line).

    >>> link_ranges([0, 1, 2, 3, 7, 9, 10])
    '0–3, 7, 9–10'
    >>> link_ranges([0, 2, 4, 6, 8], limit=2)
    '0, 2 and 3 more (5 links in all)'
    """
    out, run = [], []
    ks = sorted(set(int(x) for x in links))
    for k in ks:
        if run and k == run[-1] + 1:
            run.append(k)
            continue
        if run:
            out.append(f"{run[0]}–{run[-1]}" if len(run) > 1 else f"{run[0]}")
        run = [k]
    if run:
        out.append(f"{run[0]}–{run[-1]}" if len(run) > 1 else f"{run[0]}")
    if len(out) > limit:
        return f"{', '.join(out[:limit])} and {len(out) - limit} more ({len(ks)} links in all)"
    return ", ".join(out)


@dataclass(frozen=True, slots=True)
class HostEvent:
    """Something the host reports: ``kind`` in {"silent", "recovered" (a silent link speaks again),
    "nack", "no_ack", "unknown_chip", "missing_chip", "announce" (a chip rebooted), "recovery" (rebooted
    chips streaming again), "reconnect", "not_a_sheet", "sync", "resync", "stray", and `host.health`'s
    "health_magnitude", "health_magnitude_ok", "health_bias_shift"}; ``link``/``node``/``uid`` where known;
    ``detail`` text."""

    t: float
    kind: str
    detail: str
    link: int | None = None
    node: int | None = None
    uid: int | None = None
