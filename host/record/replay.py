"""Replay as a transport: recorded wire input fed through the same decoder, aggregator and estimator.

A recording's raw input (``/capsheet/raw/bus{N}`` of a capsheet MCAP, `host.record.recording`) or a CAN log
that python-can reads (candump ``.log``, Vector ``.asc``/``.blf``; ``capsheet host --can-log``)
is played back one bus per `ReplayTransport`: serial bytes go through the serial transport's
`protocol.framing.StreamDecoder`, CAN frames through `host.transport.ports.CanTransport`'s own decode
step, so events come out exactly as the live transports produce them.

`Replay` merges the buses in recorded time order and drives an `host.snapshots.aggregator.Aggregator` on a
simulated clock (the recorded host clock): the counters open where the host opened them (the
recorded ``/capsheet/sync``; a CAN log has none, so a counter opens at its first frame), deadlines
pass in recorded time, and the node map and calibration are the recording's (``calibration.json``;
a CAN log gets node ``k`` -> link ``k - 1``, nominal sensitivity and a `CAN_LOG_DEADLINE_S` deadline). Counters whose deadline
passed are emitted when the host emitted them (the recorded ``timestamp + latency_s``: a loaded
host's threads poll late, and frames that came in meanwhile made it into the snapshot). The snapshots are then those
the host made, whatever the speed: ``speed=None`` as fast as possible, ``speed=1.0`` real time.

    from host.record.replay import Replay
    for snap in Replay("run.mcap").snapshots():
        ...
"""

from __future__ import annotations

import base64
import heapq
import struct
import time
import zlib
from pathlib import Path
from types import SimpleNamespace
from typing import Iterator

import numpy as np

from protocol.constants import nominal_sensitivity
from protocol.can import CanDecoder
from protocol.framing import StreamDecoder
from protocol.lattice import Lattice

from host.snapshots.aggregator import Aggregator
from host.snapshots.snapshot import LatticeSnapshot
from host.snapshots.feed import SnapshotFeed
from host.transport.ports import Transport, TransportCapabilities, feed_can

__all__ = ["ReplayTransport", "Replay", "CAN_LOG_SUFFIXES", "load_can_log"]

CAN_LOG_SUFFIXES = (".log", ".asc", ".blf")
#: a CAN log carries no deadlines: a counter waits this long (log time) for its links
CAN_LOG_DEADLINE_S = 0.25


class ReplayTransport(Transport):
    """One recorded bus as a transport (read-only: what is sent is counted in ``sent`` and dropped).

    Parameters
    ----------
    chunks : list of (t, kind, payload)
        In recorded order: ``t`` host monotonic seconds; ``kind`` ``"serial"`` (payload: bytes) or
        ``"can"`` (payload: list of frame dicts as `host.record.recording` stores them, or can.Message).
    name : str
        The recorded port or bus name.
    speed : float or None
        None: every `recv` returns the next chunk at once. A number: chunks are due at
        ``(t - t_first) / speed`` after the first `recv` (1.0 real time); `recv` waits for them.
    """

    def __init__(self, chunks: list, name: str = "replay", *, speed: float | None = None, fd: bool = True) -> None:
        super().__init__(name)
        if speed is not None and not (np.isfinite(speed) and speed > 0):
            raise ValueError(f"Invalid speed: {speed!r} (need a number > 0, or None for as fast as possible)")
        kinds = {k for _, k, _ in chunks}
        if len(kinds) > 1:
            raise ValueError(f"Replay bus {name!r} mixes {sorted(kinds)} input")
        self.kind = kinds.pop() if kinds else "serial"
        if self.kind not in ("serial", "can"):
            raise ValueError(f"Invalid raw kind {self.kind!r} in bus {name!r}")
        self._chunks = chunks
        self._pos = 0
        self.speed = speed
        self._t_first = chunks[0][0] if chunks else 0.0
        self._wall0: float | None = None
        # the live transports' decoders: a serial stream, or CAN frames (a recording holds only
        # frames the host received, so the CAN decoder's echo filter sees none of ours)
        self.decoder = (StreamDecoder(batch_samples=True, batch_snapshots=True) if self.kind == "serial"
                        else CanDecoder(fd=fd))
        self.sent: list = []
        self.capabilities = TransportCapabilities(kind=self.kind, mtu=1018 if self.kind == "serial" else 64,
                                                  fd=self.kind == "can" and fd, name=name)

    @property
    def exhausted(self) -> bool:
        return self._pos >= len(self._chunks)

    @property
    def next_time(self) -> float | None:
        """Recorded time of the next chunk (None when exhausted)."""
        return None if self.exhausted else float(self._chunks[self._pos][0])

    def __len__(self) -> int:
        return len(self._chunks)

    def _recv_internal(self, timeout_s: float | None) -> list:
        if self.exhausted:
            if timeout_s:
                time.sleep(min(timeout_s, 0.05))
            return []
        t, kind, payload = self._chunks[self._pos]
        if self.speed is not None:
            now = time.monotonic()
            if self._wall0 is None:
                self._wall0 = now
            due = self._wall0 + (t - self._t_first) / self.speed
            if due > now:
                wait = due - now if timeout_s is None else min(due - now, timeout_s)
                time.sleep(wait)
                if time.monotonic() < due:
                    return []
        self._pos += 1
        if kind == "serial":
            self.stats.bytes_in += len(payload)
            return self.decoder.feed(payload)
        return feed_can(self.decoder, [_frame(f) for f in payload], self.stats)

    def _send_internal(self, msg) -> None:
        self.sent.append(msg)


def _frame(f):
    """A recorded CAN frame (a `host.record.recording` dict, or a can.Message from a log) with can.Message's
    attributes."""
    if not isinstance(f, dict):
        return f
    return SimpleNamespace(arbitration_id=f["id"], data=base64.b64decode(f["data"]), is_extended_id=f["ext"],
                           is_fd=f["fd"], is_error_frame=f["err"], is_remote_frame=f["rtr"],
                           bitrate_switch=f.get("brs", False), timestamp=f.get("ts", 0.0))


def load_can_log(path) -> dict[str, list]:
    """A python-can log (.log, .asc, .blf) as ``{channel: [(t, "can", [can.Message]), ...]}``.

    Received frames only (``is_rx``); one chunk per frame, ``t`` the log's timestamp.
    """
    import can

    path = Path(path)
    if path.suffix.lower() not in CAN_LOG_SUFFIXES:
        raise ValueError(f"{str(path)!r}: not a CAN log python-can reads here (need {', '.join(CAN_LOG_SUFFIXES)})")
    from can.io.blf import BLFParseError

    from protocol.files import open_regular
    with open_regular(path, "a CAN log") as f:  # a regular file: not a FIFO, not /dev/zero (ValueError)
        if path.suffix.lower() == ".blf":  # its sizes and containers bounded before python-can trusts them
            from host.record.blf_check import check_blf
            check_blf(f, str(path))
    buses: dict[str, list] = {}
    try:
        for m in can.LogReader(str(path)):
            if not getattr(m, "is_rx", True):
                continue
            buses.setdefault(str(m.channel), []).append((float(m.timestamp), "can", [m]))
    except (ValueError, OSError, EOFError, struct.error, IndexError, KeyError, TypeError, UnicodeDecodeError,
            zlib.error, MemoryError, BLFParseError) as exc:  # python-can's readers, on a file not what it says
        raise ValueError(f"{str(path)!r}: cannot read as a CAN log: {type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:120] if str(exc) else ''}") from None
    return buses


def _config_imu_in_log(buses: dict) -> tuple[int, int] | None:
    """The (gyro_range, mag_range) of the first CONFIG_IMU (§16.2) with format 1 or 2 in a CAN log's
    frames, or None."""
    from protocol.can import decode_can, split_id
    from protocol.messages import ConfigImu, MsgType

    for chunks in buses.values():
        for _t, _kind, frames in chunks:
            for f in frames:
                if not getattr(f, "is_extended_id", True) or split_id(f.arbitration_id)[1] != MsgType.CONFIG_IMU:
                    continue
                m = decode_can(f.arbitration_id, bytes(f.data), is_fd=bool(getattr(f, "is_fd", False)))
                if isinstance(m, ConfigImu) and m.format in (1, 2) and m.gyro_range <= 4 and m.mag_range <= 3:
                    return int(m.gyro_range), int(m.mag_range)
    return None


class Replay:
    """A recording (capsheet MCAP or CAN log) replayed into snapshots.

    Parameters
    ----------
    path : str or Path
        ``*.mcap`` written by capsheet, or a CAN log (``.log``, ``.asc``, ``.blf``).
    speed : float or None
        None as fast as possible; 1.0 real time (the recorded pace); 2.0 twice as fast.
    lattice : str or Lattice, optional
        Needed for a CAN log (it has no session facts); ignored for MCAP.
    link_length : float, optional
        Metres; default the recording's (CAN log: 0.01).
    deadline_s : float, optional
        A completion deadline of your own: counters are then emitted where it falls. Default: an
        MCAP recording's counters are emitted where the host emitted them (its deadline adapted
        as it ran; the recording holds each emission), a CAN log's after `CAN_LOG_DEADLINE_S`.
    imu_ranges : (gyro_range, mag_range), optional
        A CAN log's gyroscope and magnetometer range codes (docs/protocol.md §16.2). Default: those of
        the first CONFIG_IMU with format 1 or 2 the log holds (a bus log sees the host's commands),
        else CONFIG_IMU's power-on values (±1000 °/s, ±4 gauss); `imu_ranges_from` says which.
        An MCAP recording's are its session's.

    Attributes
    ----------
    recording : host.record.Recording or None
    transports : list of ReplayTransport
    aggregator : Aggregator
    """

    def __init__(self, path, *, speed: float | None = None, lattice: str | Lattice | None = None,
                 link_length: float | None = None, deadline_s: float | None = None,
                 imu_ranges: tuple[int, int] | None = None) -> None:
        from host.record.mcap_read import malformed, malformed_errors
        try:  # a recording whose session, calibration or transports are not what capsheet writes: one line
            self._open(path, speed, lattice, link_length, deadline_s, imu_ranges)
        except malformed_errors() as exc:
            raise malformed(path, exc) from None

    def _open(self, path, speed, lattice, link_length, deadline_s, imu_ranges) -> None:
        from host.record import recording as record

        source = [str(p) for p in path] if isinstance(path, (list, tuple)) else path
        self.path = Path(source[0] if isinstance(source, list) else source)
        self.speed = speed
        self.recording = None
        self.imu_ranges_from = "session"  # an MCAP recording: its session's CONFIG_IMU
        self._syncs = np.zeros((0, 2))
        self._host_calibration = None
        calibration = None
        session: dict = {}
        fds: dict = {}
        if self.path.suffix.lower() == ".mcap":
            self.recording = rec = record.read(source)  # a split set too
            session = rec.session
            self.lattice = rec.lattice
            recorded = session.get("transports", [])
            names = {i: t.get("name", f"bus{i}") for i, t in enumerate(recorded)}
            buses = {names.get(b, f"bus{b}"): rec.raw[b] for b in sorted(rec.raw)}
            # a bus the host opened classic dropped the CAN FD frames it got: so does its replay
            fds = {names.get(b, f"bus{b}"): bool(recorded[b].get("fd", True)) if b < len(recorded) else True
                   for b in rec.raw}
            self._syncs = rec.sync
            calibration = rec.attachments.get("calibration.json")
            host_cal = rec.attachments.get(record.HOST_CALIBRATION)
            if host_cal is not None:  # `capsheet host --calibration`: the snapshots were corrected with it
                from host.analysis.calibration import Calibration
                self._host_calibration = Calibration.from_dict(host_cal, f"{self.path.name}: "
                                                                          f"{record.HOST_CALIBRATION}")
            if not buses:
                raise ValueError(f"{str(self.path)!r} holds no raw input (/capsheet/raw/bus*): nothing to replay")
        else:
            if lattice is None:
                raise ValueError(f"{str(self.path)!r} is a CAN log: give the lattice (e.g. --lattice 14x14)")
            self.lattice = Lattice.parse(lattice) if isinstance(lattice, str) else lattice
            buses = load_can_log(self.path)
            if not buses:
                raise ValueError(f"{str(self.path)!r} holds no received CAN frame")
            if imu_ranges is None:
                imu_ranges = _config_imu_in_log(buses)
                self.imu_ranges_from = "default" if imu_ranges is None else "CONFIG_IMU in the log"
            else:
                self.imu_ranges_from = "given"
        self.link_length = float(link_length if link_length is not None else session.get("link_length_m", 0.01))
        rate = float(session.get("rate_hz", 100.0))
        self._own_deadline = deadline_s is not None
        if deadline_s is not None:
            dl = deadline_s
        elif self.recording is not None:
            dl = session.get("deadline_s", max(2.0 / rate, 0.05))
        else:
            dl = CAN_LOG_DEADLINE_S
        self.transports = [ReplayTransport(chunks, name, fd=fds.get(name, True)) for name, chunks in buses.items()]
        self._now = min((t.next_time for t in self.transports if t.next_time is not None), default=0.0)
        n = self.lattice.n_links
        # wall clock of the recording: LatticeSnapshot.wall_time = timestamp + offset (a CAN log's
        # times are Unix times already)
        self._wall_offset = 0.0
        self._wall_at: dict = {}
        if self.recording is not None and len(self.recording):
            self._wall_offset = float(self.recording.wall_time[0] - self.recording.timestamp[0])
            # the offset each counter had: the host measures Unix minus monotonic as it opens a
            # counter, and on a loaded machine a thread that waits between reading the two clocks
            # moves that measurement by milliseconds; one offset for the whole recording gave some
            # snapshots (and every ROS 2 message stamped from them) a wall time the host never gave
            rec = self.recording
            self._wall_at = {(c, ts): w - ts for c, ts, w in zip(rec.counter.tolist(), rec.timestamp.tolist(),
                                                                 rec.wall_time.tolist())}
        # an MCAP recording's counters are emitted where the host emitted them (`snapshots`), never
        # at a deadline of this aggregator's own, which would cut a read the host took in whole
        self._follows = self.recording is not None and len(self.recording) > 0 and not self._own_deadline
        self.aggregator = Aggregator(n, n_buses=len(self.transports), deadline_s=float(dl), queue_size=1 << 30,
                                     emit_at_deadline=not self._follows)
        imu = session.get("imu_config") if self.recording is not None else None
        if imu:  # 6/9-axis chips: their records converted at the ranges the host gave them (§16.2)
            self.aggregator.gyro_range, self.aggregator.mag_range = int(imu[1]), int(imu[2])
            self.aggregator.imu_format = int(imu[0])
        elif self.recording is None and imu_ranges is not None:  # a CAN log
            self.aggregator.gyro_range, self.aggregator.mag_range = int(imu_ranges[0]), int(imu_ranges[1])
        # the host's feed on the recorded clock: the same correction (the recorded host calibration),
        # applied where the host applied it
        self.feed = SnapshotFeed(self.aggregator, clock=lambda: self._now, queue_size=1 << 30,
                                 wall_clock=lambda: self._now + self._wall_offset)
        self.host_calibration = self._host_calibration
        if calibration is not None:
            self._apply_calibration(calibration)

    def _apply_calibration(self, cal: dict) -> None:
        """The node map, offsets and sensitivities exactly as `host.session.core.Host` set them."""
        from host.record.mcap_read import check_chip_calibration
        n = self.lattice.n_links
        check_chip_calibration(cal, n, self.path, need_node=True)  # links in the lattice, 16-bit nodes, finite
        lut = np.full(1 << 16, -1, dtype=np.int64)
        unassigned = np.ones(n, dtype=bool)
        scale_nominal = nominal_sensitivity(int(cal.get("range_code", 0)))
        off = np.zeros((n, 3))
        sens = np.full((n, 3), scale_nominal)
        for c in cal.get("links", []):
            k = int(c["link"])
            lut[int(c["node"])] = k
            unassigned[k] = False
            off[k] = c["offset"]
            sens[k] = c["sensitivity"]
        if cal.get("links"):
            self.feed.set_map(lut, unassigned)
        self.feed.set_calibration(off, sens)

    @property
    def host_calibration(self):
        """The calibration every snapshot is corrected with, as the recording host did (its
        ``host_calibration.json``), or None; settable (None replays the uncorrected snapshots)."""
        return self._host_calibration

    @host_calibration.setter
    def host_calibration(self, cal) -> None:
        self._host_calibration = cal
        self.feed.set_correction(None if cal is None else cal.apply)

    @property
    def duration_s(self) -> float:
        """Recorded time from the first to the last raw chunk, seconds."""
        ts = [c[0] for t in self.transports for c in t._chunks]
        return float(max(ts) - min(ts)) if ts else 0.0

    @property
    def n_chunks(self) -> int:
        return sum(len(t) for t in self.transports)

    def snapshots(self, progress=None, recorder=None) -> Iterator[LatticeSnapshot]:
        """Every snapshot the recorded input makes, in counter order.

        ``progress``: called with the number of raw chunks consumed so far (e.g. a tqdm update).
        ``recorder``: a `host.record.recording.Recorder` that gets the raw input and SYNCs again, with their
        recorded times (so a re-recording replays too).
        """
        feed = self.feed
        syncs = [(float(t), 0, int(c)) for c, t in self._syncs.tolist()]
        heap: list = []
        for bus, tr in enumerate(self.transports):
            if tr.next_time is not None:
                heapq.heappush(heap, (tr.next_time, 1, bus))
        si = 0
        ei = 0
        emits = None
        if self._follows:
            e = self.recording.timestamp + self.recording.latency_s
            order = np.argsort(e, kind="stable")
            emits = list(zip(e[order].tolist(), self.recording.counter[order].tolist()))
        first_sync = True
        wall0 = time.monotonic()
        t_first = min([h[0] for h in heap] + [s[0] for s in syncs[:1]], default=0.0)
        done = 0
        while heap or si < len(syncs):
            # the next thing in recorded time: a SYNC the host opened, or a raw chunk
            if si < len(syncs) and (not heap or syncs[si][0] <= heap[0][0]):
                t, kind, who = syncs[si]
                si += 1
            else:
                t, kind, who = heapq.heappop(heap)
            if self.speed is not None:
                due = wall0 + (t - t_first) / self.speed
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            if emits is None:
                feed.poll(max(self._now, t))  # a CAN log, or a deadline of one's own: as they fall
            else:
                # the host emitted a counter at its deadline *when its threads got to it*: poll when
                # it did, so the frames that made it in live make it in here
                while ei < len(emits) and emits[ei][0] < t:  # an emission at t came with the ingest at t
                    # at the host's deadline, which adapted as it ran: the recorded decision, not ours
                    feed.emit_through(emits[ei][1], max(self._now, emits[ei][0]))
                    ei += 1
            self._now = max(self._now, t)
            if kind == 0:
                if recorder is not None:
                    recorder.sync(who, t)
                self._wall_offset = self._wall_at.get((who, t), self._wall_offset)
                feed.open_counter(who, t, restart=first_sync)
                first_sync = False
            else:
                tr = self.transports[who]
                if recorder is not None:
                    _, rkind, payload = tr._chunks[tr._pos]
                    if rkind == "can":
                        payload = [_frame(f) for f in payload]
                    recorder.raw(who, rkind, payload, tr.name, t=t)
                events = tr.recv(0)
                feed.ingest(events, who, self._now)
                if tr.next_time is not None:
                    heapq.heappush(heap, (tr.next_time, 1, who))
                done += 1
                if progress is not None:
                    progress(done)
            if feed.pending:
                yield from feed.drain()
        self._now += self.aggregator.deadline_s
        feed.poll(self._now)
        feed.flush(self._now)
        yield from feed.drain()

    @property
    def stats(self) -> dict:
        return {"aggregator": self.aggregator.stats.summary(),
                "buses": [{"name": t.name, "kind": t.kind, "chunks": len(t), **t.stats.as_dict()}
                          for t in self.transports]}
