"""What the aggregator hands out: the `LatticeSnapshot` (with its per-link `LinkFlag`), the counts
it keeps (`AggregatorStats`), and completeness over a window of SYNCs (`window_completeness`).

The aggregator itself (`host.snapshots.aggregator`) makes them; everything that reads snapshots —
the feed's consumers, the recorder, the estimator's process — needs only this module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag

import numpy as np

from protocol.constants import SampleStatus

__all__ = ["LinkFlag", "LatticeSnapshot", "AggregatorStats", "window_completeness"]


class LinkFlag(IntFlag):
    """Per-link status of a `LatticeSnapshot`: the 4 SampleStatus bits from the wire (bits 0..3)
    plus what the host knows (bits 4..7)."""

    OK = 0
    SATURATED = SampleStatus.SATURATED  #: 0x01 wire: an axis hit the ADC limit
    SELF_TEST = SampleStatus.SELF_TEST  #: 0x02 wire: self-test excitation on
    STALE = SampleStatus.STALE  #: 0x04 wire: repeated previous value
    INVALID = SampleStatus.INVALID  #: 0x08 wire: the chip (or gateway) says no data
    MISSING = 0x10  #: host: no frame for this link arrived by the deadline
    SILENT = 0x20  #: host: the watchdog marks this link's chip as fallen silent
    UNASSIGNED = 0x40  #: host: no chip is assigned to this link


@dataclass(frozen=True, slots=True, eq=False)
class LatticeSnapshot:
    """All links' readings for one SYNC counter.

    Attributes
    ----------
    counter : int
        The SYNC counter (u16) the samples answer.
    timestamp : float
        Host monotonic seconds (the ``now`` the aggregator was given) when the counter opened: when
        the host sent (or saw) its SYNC, else when its first frame arrived.
    wall_time : float
        ``timestamp + Aggregator.wall_offset``: Unix time of the same instant (for recordings).
    readings : ndarray, shape (n_links, 3), float64
        Specific force in m/s², sensor frame (docs/design.md), after per-chip calibration
        (`protocol.constants.counts_to_si`); NaN where not ``valid``.
    valid : ndarray, shape (n_links,), bool
        A frame arrived for the link and its status is not INVALID.
    status : ndarray, shape (n_links,), uint8
        `LinkFlag` bits per link.
    complete : bool
        Every expected link arrived (emitted on completion, not at the deadline).
    latency_s : float
        ``emitted - timestamp``: from SYNC (or first frame) to emission.
    first_frame_s, last_frame_s : float
        Arrival of the first / last frame after ``timestamp`` (seconds; NaN if none).
    counts : ndarray, shape (n_links, 3), int16, or None
        The chips' ADC counts the readings were converted from (0 where not ``valid``): what a
        recording stores (docs/recording.md); None for a snapshot made without an aggregator.
    gyro : ndarray, shape (n_links, 3), float64, or None
        6/9-axis chips (docs/protocol.md §16): angular rate in rad/s, sensor frame, nominal
        sensitivity at the aggregator's ``gyro_range``; NaN where no record came. None for accelerometer-only
        chips (an aggregator told the chips' IMU format gives every snapshot the array, all NaN when no
        record of the counter came; without it, None when none came).
    mag : ndarray, shape (n_links, 3), float64, or None
        Magnetic flux density in tesla at ``mag_range`` (9-axis records); None without any.
    sample_time_s : ndarray, shape (n_links,), float64, or None
        Each record's ``time_us`` in seconds after the SYNC; NaN where unknown. None with ``gyro``.
    """

    counter: int
    timestamp: float
    wall_time: float
    readings: np.ndarray
    valid: np.ndarray
    status: np.ndarray
    complete: bool
    latency_s: float
    first_frame_s: float = float("nan")
    last_frame_s: float = float("nan")
    counts: np.ndarray | None = None
    gyro: np.ndarray | None = None
    mag: np.ndarray | None = None
    sample_time_s: np.ndarray | None = None

    @property
    def n_links(self) -> int:
        return int(self.valid.shape[0])

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.valid))

    @property
    def completeness(self) -> float:
        return self.n_valid / max(1, self.n_links)


@dataclass
class AggregatorStats:
    """Counters of an `Aggregator`. Arrays are per link (index = lattice address) or per bus."""

    n_links: int
    n_buses: int = 1
    samples: int = 0  #: samples accepted into an open counter
    emitted: int = 0
    complete: int = 0  #: emitted complete
    incomplete: int = 0  #: emitted at the deadline (or evicted) with links missing
    evicted: int = 0  #: emitted early because ``max_open`` counters were open
    dropped: int = 0  #: emitted but dropped from the output queue (consumer too slow)
    late: int = 0  #: frames for a counter already emitted or too old
    duplicates: int = 0
    unknown: int = 0  #: frames from nodes the layout does not know
    out_of_range: int = 0  #: SNAPSHOT samples beyond the lattice
    assigned_links: int = 0  #: sum over emitted snapshots of the links with a chip assigned
    valid_links: int = 0  #: sum over emitted snapshots of the assigned links with a valid sample
    imu_links: int = 0  #: sum over emitted snapshots of the links with a valid IMU record (gyroscope, §16)
    mag_links: int = 0  #: ... of them, with a magnetometer (9-axis records)
    deadline_changes: int = 0  #: times the adaptive deadline moved (late raises included)
    late_raises: int = 0  #: times a late frame raised the adaptive deadline at once
    input_holds: int = 0  #: counters past their deadline held until the input was read past it
    stray: int = 0  #: frames for a counter nobody sent (drive) or out of the sequence (follow): dropped
    resyncs: int = 0  #: follow mode: the counter sequence restarted or jumped and was followed
    unknown_nodes: dict = field(default_factory=dict)  #: node -> frames (at most 256 nodes kept)
    link_frames: np.ndarray = None  # type: ignore[assignment]
    link_late: np.ndarray = None  # type: ignore[assignment]
    link_duplicates: np.ndarray = None  # type: ignore[assignment]
    link_missing: np.ndarray = None  # type: ignore[assignment]  #: snapshots emitted without the link
    link_latency_s: np.ndarray = None  # type: ignore[assignment]  #: EWMA of frame arrival - SYNC
    link_last_seen: np.ndarray = None  # type: ignore[assignment]  #: monotonic time of the last frame
    bus_frames: np.ndarray = None  # type: ignore[assignment]
    bus_late: np.ndarray = None  # type: ignore[assignment]
    bus_duplicates: np.ndarray = None  # type: ignore[assignment]
    bus_unknown: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        n, b = self.n_links, self.n_buses
        for name in ("link_frames", "link_late", "link_duplicates", "link_missing"):
            setattr(self, name, np.zeros(n, dtype=np.int64))
        self.link_latency_s = np.full(n, np.nan)
        self.link_last_seen = np.full(n, -np.inf)
        for name in ("bus_frames", "bus_late", "bus_duplicates", "bus_unknown"):
            setattr(self, name, np.zeros(b, dtype=np.int64))

    def summary(self) -> dict:
        return {k: getattr(self, k) for k in ("samples", "emitted", "complete", "incomplete", "evicted",
                                              "dropped", "late", "duplicates", "unknown", "out_of_range",
                                              "assigned_links", "valid_links", "imu_links", "mag_links", "deadline_changes",
                                              "late_raises", "input_holds",
                                              "stray", "resyncs")}


def window_completeness(snapshots, first_counter: int, end_counter: int, syncs_sent: int | None = None) -> dict:
    """Completeness over one window of SYNCs: the counters ``first_counter`` .. ``end_counter - 1``
    (mod 2^16) the host sent in it. ``snapshots``: ``(counter, complete)`` of every snapshot emitted
    during and after the window, in emission order. Numerator and denominator are the same set of
    SYNCs: a snapshot of a SYNC sent before the window (completed inside it) or after it is not
    counted, a SYNC of the window whose snapshot never came (or was dropped) counts as incomplete.
    (The bench used to divide the snapshots completed in the window by the SYNCs sent in it: up to
    100.83 %; ``capsheet demo`` printed 100.1 %.)

    A window longer than 2^16 SYNCs (7.5 min at 145 Hz) needs ``syncs_sent``, the host's count of
    SYNCs sent in it (``Host.syncs_sent`` difference, off by a SYNC or two if read while it sends):
    the window's length is the value congruent to ``end - first`` mod 2^16 nearest to it, and the
    counters are unwrapped one snapshot after the other (consecutive emissions are far less than
    2^15 SYNCs apart)."""
    sent = (end_counter - first_counter) & 0xFFFF
    if syncs_sent is not None:
        sent = syncs_sent + ((((sent - syncs_sent) + 0x8000) & 0xFFFF) - 0x8000)
    seen: dict[int, bool] = {}
    pos, prev = 0, first_counter & 0xFFFF  # unwrapped position of the last counter (first = 0)
    for counter, complete in snapshots:
        c = counter & 0xFFFF
        pos += (((c - prev) + 0x8000) & 0xFFFF) - 0x8000
        prev = c
        if 0 <= pos < sent:
            seen[pos] = seen.get(pos, False) or bool(complete)
    complete = sum(seen.values())
    return {"syncs_sent": sent, "snapshots": len(seen), "complete": complete,
            "complete_pct": round(100.0 * complete / sent, 2) if sent else 0.0}
