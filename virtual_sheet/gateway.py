"""Gateways: the sans-I/O middle of every virtual device, between a host and a sheet's chips.

A `Gateway` takes what the host sends (`feed` serial bytes, or `receive` CAN frames), decodes
every frame **once** and hands it with its decode to the chips it concerns (SYNC and other
broadcasts: every chip; an addressed frame: the chips with that node id; a frame that does not
decode: every chip, which counts it), and queues what the chips answer for the host, after the
stream faults (`faults.FrameFaults`). `pop_output(now_s)` returns what is due.

* **A node on the wire** (docs/protocol.md §13): a gateway that packs or generates SYNC is a
  gateway node (`GatewayNode`): it announces itself (ANNOUNCE, INFO with capability GATEWAY,
  GATEWAY_INFO with its flags and link runs), takes ASSIGN, GET_INFO and RESET, sends STATUS once
  assigned and refuses chip commands with NACK UNSUPPORTED — so a host learns packing and the SYNC
  source from it. A gateway that does neither is a transparent bridge: no node, no frames of its own.
* **Per-chip mode**: every chip's frames go to the host as they are (SAMPLE per chip).
* **Packed mode** (``packed=True``): the gateway answers a SYNC with SNAPSHOT frames that pack
  the samples of every link it covers for that counter (at most 202 samples per serial frame,
  11 per CAN FD frame; links whose chip did not answer by `SNAPSHOT_DEADLINE_S` — a chip whose
  reply delay is longer — are sent as INVALID with counts 0, and their late SAMPLE is dropped). The
  SNAPSHOT comes from the gateway's node id. Every other chip frame is forwarded unchanged.
  On a 6/9-axis sheet (``sensors``) it packs the chips' IMU records into SNAPSHOT_IMU instead
  (docs §16.5: at most 77/53 records per serial frame, 4/3 per CAN FD frame; a link not heard is an
  INVALID record), says so in GATEWAY_INFO (``sample_format`` 1 or 2), and configures its chips itself:
  CONFIG_IMU of its format before it passes START on to a chip still in format 0.
* **SYNC source** (``sync_rate_hz``): the gateway itself broadcasts SYNC at that rate to its
  chips and forwards each SYNC to the host (a host then "follows the gateway's SYNC"). It is its
  segment's only SYNC source (§5.1, §13.3): SYNC frames from the host are not passed to the chips,
  they are counted (``stats.syncs_refused``, and STATUS ``missed_syncs``).
* **SYNC line** (``followers``): gateways of one sheet on separate links (two serial gateways, each
  with half the chips) share one SYNC: the leader (the one with ``sync_rate_hz``) hands every SYNC
  it generates to its followers at the same instant, as a wired SYNC line between gateway boards
  would; each follower broadcasts it to its own chips and forwards it to its own host port, so every
  port's stream carries the SYNC before the samples that answer it.

A sheet with the array engine (`chiparray.ChipArray`) is served in batch: a SYNC is one numpy
step for every chip behind the gateway; per-chip serial frames stay one byte string in the
queue until `pop_output` is asked for them one by one (`pop_wire`, what a serial device sends,
never splits them), and in packed mode the sample words go into the SNAPSHOT straight from the
arrays (nothing encoded, nothing decoded again). The frames are the same as with one chip
object each (tests/virtual_sheet/test_chiparray.py).

Time is passed in (``now_s``); nothing here reads a clock or touches a port.
"""

from __future__ import annotations

import struct
from typing import Any, Sequence

import numpy as np

from protocol.can import MAX_FD_IMU_RECORDS, MAX_FD_SNAPSHOT_SAMPLES, CanFrame, decode_can, imu_can_frames, to_can
from protocol.capacity import MAX_SERIAL_SNAPSHOT_SAMPLES
from protocol.constants import SampleStatus
from protocol.framing import (MAX_ENCODED_SIZE, SAMPLE_WIRE_SIZE, DecodeError, StreamDecoder, decode_frame, encode,
                              encode_frame)
from protocol.messages import (LINK_NONE, NODE_BROADCAST, Assign, Capability, ChipState, GatewayFlag, Message,
                               MsgType, SampleFormat, Snapshot, Sync, pack_sample_words, IMU_RECORD_SIZE,
                               MAX_SERIAL_IMU_RECORDS, TIME_UNKNOWN, ConfigImu, ImuAccel, ImuGyro, ImuMag, ImuSample,
                               Sample, SnapshotImu, Start, pack_imu_records, unpack_imu_records)
from protocol.state import SNAPSHOT_DEADLINE_S

from .faults import ERROR_FRAME, FaultSpec, FaultStats, FrameFaults
from .gateway_node import FIRMWARE_VERSION, GatewayNode, gateway_uid

__all__ = ["Gateway", "GatewayStats", "GatewayNode", "CHIP_POLL_PERIOD_S", "gateway_uid", "FIRMWARE_VERSION"]

CHIP_POLL_PERIOD_S = 0.01  #: how often the chips' timers (heartbeat, re-announce) are served


_INVALID_WORD = int(SampleStatus.INVALID) << 36  #: the sample word of a link nobody answered for
_FIELD_SHIFT = np.array([1, 1 << 12, 1 << 24], dtype=np.int64)  # x, y, z into a sample word
_SNAP_HDR = struct.Struct("<HHB")  # SNAPSHOT payload header: counter, first_link, count
_SNAP_IMU_HDR = struct.Struct("<HHBB")  # SNAPSHOT_IMU payload header: counter, first_link, count, format
assert _SNAP_IMU_HDR.size == SnapshotImu.HEADER_SIZE == 6
#: the SNAPSHOT_IMU format a packing gateway of a sheet with these sensors packs (docs §16.5)
PACKED_IMU_FORMAT = {"accel": 0, "accel+gyro": int(SampleFormat.IMU6), "accel+gyro+mag": int(SampleFormat.IMU9)}


def _frame_chunks(covered: np.ndarray, cap: int) -> list[tuple[int, int, int]]:
    """How a packing gateway splits its covered links (sorted) into frames of at most ``cap``:
    ``(first link, position in covered, count)`` per frame, a frame never spanning a gap (its links
    are ``first .. first + count - 1``)."""
    chunks = []
    pos = 0
    for run in np.split(covered, np.flatnonzero(np.diff(covered) != 1) + 1):
        for i in range(0, run.size, cap):
            m = min(cap, run.size - i)
            chunks.append((int(run[i]), pos, m))
            pos += m
    return chunks


class _Run:
    """A queue entry of ``n`` frames of ``size`` bytes each, back to back in ``data`` (a serial
    SYNC's SAMPLE frames from the chip array: no Python object per frame until one is asked for)."""

    __slots__ = ("data", "n", "size")

    def __init__(self, data: bytes, n: int, size: int) -> None:
        self.data, self.n, self.size = data, n, size

    def frames(self) -> list[bytes]:
        d, z = self.data, self.size
        return [d[i:i + z] for i in range(0, len(d), z)]


class GatewayStats:
    """Counters of one gateway."""

    __slots__ = ("host_frames", "host_errors", "host_bytes", "syncs", "syncs_generated", "syncs_refused",
                 "chip_frames", "snapshots", "frames_to_host", "late_dropped", "imu_configured")

    def __init__(self) -> None:
        for s in self.__slots__:
            setattr(self, s, 0)

    def as_dict(self) -> dict[str, int]:
        return {s: getattr(self, s) for s in self.__slots__}


class Gateway:
    """Frames between a host and some chips of a `VirtualSheet` (module docstring).

    Parameters
    ----------
    sheet : VirtualSheet
        Owns the chips, the readings and the truth record.
    links : sequence of int, optional
        The links whose chips sit behind this gateway (default: all). On CAN, one gateway per bus.
    packed : bool
        Answer SYNC with SNAPSHOT frames.
    sync_rate_hz : float, optional
        Generate SYNC at this rate.
    faults : FaultSpec, optional
        Stream faults on the frames to the host (default: the sheet's).
    stream : int
        Distinguishes the fault random streams of several gateways of one sheet (and their uids).
    as_node : bool, optional
        Be a gateway node on the wire (docs/protocol.md §13.1); default: when it packs or is a SYNC
        source (the spec requires it then), else a transparent bridge.
    """

    #: the class of its node on the wire (a subclass: the conformance suite's broken gateways)
    node_class: type = GatewayNode
    #: how long after a SYNC it sends that SYNC's packed frames, at the earliest: 0 sends them as soon as
    #: every chip answered; a gateway that flushes on a timer sends them later — docs §13.2 allows anywhere
    #: up to `SNAPSHOT_DEADLINE_S` (10 ms) after the SYNC (a subclass sets it: the conformance suite's
    #: healthy gateways flush at 5 and 10 ms)
    flush_s: float = 0.0

    def __init__(self, sheet, links: Sequence[int] | None = None, *, packed: bool = False,
                 sync_rate_hz: float | None = None, faults: FaultSpec | None = None,
                 fault_stats: FaultStats | None = None, stream: int = 0, as_node: bool | None = None) -> None:
        if not 0.0 <= self.flush_s <= SNAPSHOT_DEADLINE_S:
            raise ValueError(f"Invalid flush_s: {self.flush_s} (0..{SNAPSHOT_DEADLINE_S} s, docs §13.2)")
        self.sheet = sheet
        self.can = sheet.transport == "can"
        self.fd = sheet.fd
        self.links = list(range(sheet.n_links) if links is None else links)
        self.chips = [sheet.chips[k] for k in self.links]
        self.delays = [sheet.reply_delay_s[k] for k in self.links]
        self._late = any(self.delays)
        self.packed = packed
        if packed and self.can and not self.fd:
            raise ValueError("Packed mode on CAN needs CAN FD (a SNAPSHOT does not fit 8 bytes)")
        self.max_per_frame = MAX_FD_SNAPSHOT_SAMPLES if self.can else MAX_SERIAL_SNAPSHOT_SAMPLES
        self.sync_rate_hz = sync_rate_hz
        self.spec = faults if faults is not None else sheet.faults
        self.fault_stats = fault_stats if fault_stats is not None else sheet.fault_stats
        self.faults = FrameFaults(self.spec, self.fault_stats, can=self.can, stream=stream) \
            if self.spec.any_stream else None
        self.stats = GatewayStats()
        self._rx = bytearray()
        self._rx_discard = False
        self._queue: list[tuple[float, Any]] = []  # (due, frame or _Run), in due order
        self._runs = 0  # _Run entries in the queue
        self._next_poll = 0.0
        self._next_sync: float | None = None
        self._sync_counter = 0
        self._covered = np.asarray(self.links, dtype=np.int64)
        self._cov_all = bool(self._covered.size == sheet.n_links and (self._covered == np.arange(sheet.n_links)).all())
        # SNAPSHOT frames of a SYNC: (first_link, position among the covered links, count), per
        # contiguous run of covered links, chunked to what one frame holds
        self._chunks = _frame_chunks(self._covered, self.max_per_frame)
        self._words = np.zeros(sheet.n_links, dtype=np.int64)  # packed mode: each link's sample word
        self._cov_mask = np.zeros(sheet.n_links, dtype=bool)  # the links of this gateway's runs
        self._cov_mask[self._covered] = True
        self._followers: list[Gateway] = []
        self._leader: Gateway | None = None  # set when this gateway takes another's SYNC line
        self.stream = stream
        self.as_node = as_node
        self.uid = gateway_uid(getattr(sheet, "seed", 0), stream)
        self.node: GatewayNode | None = None  #: the gateway node, once powered (None: a transparent bridge)
        self._snap_decoder = StreamDecoder(batch_samples=True)
        self.powered = False
        arr = getattr(sheet, "array", None)
        self.chip_array = arr if arr is not None and self.links == sorted(set(self.links)) else None
        if self.chip_array is not None:
            sel = np.zeros(arr.n, dtype=bool)
            sel[self.links] = True
            self._sel = None if sel.all() else sel  # None: every chip of the array (its fast paths)
            self._delay_of = np.asarray(sheet.reply_delay_s, dtype=float)
        # packed mode on a 6/9-axis sheet: IMU records into SNAPSHOT_IMU (docs §16.5), the chips
        # configured by the gateway itself (CONFIG_IMU before it passes START on)
        self.imu_format = PACKED_IMU_FORMAT.get(getattr(sheet, "sensors", "accel"), 0) if packed else 0
        if self.imu_format:
            if self.chip_array is None:
                raise ValueError("A gateway packing IMU records (SNAPSHOT_IMU) takes them from the chip array "
                                 "(engine='array'): one chip object each is not simulated")
            fmt = SampleFormat(self.imu_format)
            cap = MAX_FD_IMU_RECORDS[fmt] if self.can else MAX_SERIAL_IMU_RECORDS[fmt]
            self._imu_chunks = _frame_chunks(self._covered, cap)
            z = np.zeros((1, 3), dtype=np.int64)
            # the record of a link nobody answered for: INVALID, counts 0, time unknown (§16.1)
            self._invalid_rec = np.frombuffer(pack_imu_records(
                z, np.array([int(SampleStatus.INVALID)]), np.array([TIME_UNKNOWN]), z,
                z if fmt == SampleFormat.IMU9 else None), dtype=np.uint8)
            self._recs = np.empty((sheet.n_links, IMU_RECORD_SIZE[fmt]), dtype=np.uint8)

    # ------------------------------------------------------------------ the gateway as a node
    @property
    def followers(self) -> list:
        """Gateways that take this one's SYNC (a SYNC line): each is its own segment's SYNC source."""
        return self._followers

    @followers.setter
    def followers(self, gws) -> None:
        self._followers = list(gws)
        for g in self._followers:
            g.follow(self)

    def follow(self, leader: "Gateway | None") -> None:
        """Take ``leader``'s SYNC line (None: none); `followers` calls it for each gateway it lists."""
        self._leader = leader

    @property
    def sync_source(self) -> bool:
        """It generates its segment's SYNC (or takes it from a leader's SYNC line): host SYNC is refused."""
        return bool(self.sync_rate_hz) or (self._leader is not None and self._leader.sync_source)

    @property
    def node_id(self) -> int:
        """The node id its SNAPSHOT frames come from (0 for a transparent bridge)."""
        return self.node.node if self.node is not None else 0

    def _link_runs(self) -> list[tuple[int, int]]:
        out = []
        for run in np.split(self._covered, np.flatnonzero(np.diff(self._covered) != 1) + 1):
            if run.size:
                out.append((int(run[0]), int(run.size)))
        return out

    def _make_node(self) -> GatewayNode:
        can_pack = not self.can or self.fd
        caps = (Capability.SNAPSHOT if can_pack else 0) | Capability.SYNC_SOURCE
        node = self.node_class(self.uid, can=self.can, fd=self.fd, capabilities=caps)
        node.runs = self._link_runs()
        node.flags = (GatewayFlag.PACKING if self.packed else 0) | (GatewayFlag.SYNC_SOURCE if self.sync_source else 0)
        node.sample_format = self.imu_format  # what its snapshots pack: 0 words, 1/2 IMU records (§4.16, §16.5)
        rate = self.sync_rate_hz or (self._leader.sync_rate_hz if self._leader is not None else 0)
        node.sync_rate_hz = rate or 0
        return node

    # ------------------------------------------------------------------ chips
    def power_on(self, now_s: float) -> None:
        """Power the gateway node (if it is one) and every chip: their boot frames are queued."""
        self.powered = True
        out: list = []
        if self.as_node if self.as_node is not None else (self.packed or self.sync_source):
            self.node = self._make_node()
            out += self.node.power_on(now_s)
        for c in self.chips:
            out += c.power_on(now_s)
        self._emit(out, now_s)
        self._next_poll = now_s + CHIP_POLL_PERIOD_S
        if self.sync_rate_hz:
            self._next_sync = now_s

    def poll(self, now_s: float) -> None:
        """Serve the chips' timers and the gateway's own SYNC."""
        if self._next_sync is not None and now_s >= self._next_sync:
            period = 1.0 / self.sync_rate_hz
            self._next_sync += period
            if self._next_sync < now_s - 10 * period:  # fell far behind: do not burst
                self._next_sync = now_s + period
            sync = Sync(counter=self._sync_counter)
            self._sync_counter = (self._sync_counter + 1) & 0xFFFF
            self.stats.syncs_generated += 1
            frame = to_can(sync) if self.can else encode(sync)
            self._emit([frame], now_s)  # the host hears the SYNC too
            self._dispatch(frame, sync, now_s)
            for f in self.followers:  # the SYNC line: the same SYNC, at the same instant
                f.follow_sync(frame, sync, now_s)
        if now_s >= self._next_poll:
            self._next_poll = max(self._next_poll + CHIP_POLL_PERIOD_S, now_s)
            if self.node is not None:
                own = self.node.poll(now_s)
                if own:
                    self._emit(own, now_s)
            if self.chip_array is not None:
                out = self.chip_array.poll(now_s, self._sel)
            else:
                out = []
                for c in self.chips:
                    r = c.poll(now_s)
                    if r:
                        out += r
            if out:
                self._emit(out, now_s)
        if self.faults is not None:
            held = self.faults.flush(now_s)
            if held:
                self._queue.extend(held)

    def follow_sync(self, frame, sync: Sync, now_s: float) -> None:
        """A SYNC from the leader gateway's SYNC line: to this gateway's chips and its host port."""
        if not self.powered:
            return
        self._emit([frame], now_s)
        self._dispatch(frame, sync, now_s)

    def next_deadline(self) -> float:
        """When `poll` / `pop_output` next has something to do: the gateway's SYNC, the first
        frame due on the wire, the first poll tick at or after a timer of the chips or of the
        gateway node. Where those timers are not known (chips that are not the sheet's array, or
        fault wrappers and held frames, which act at any poll) every poll tick."""
        t = max(self._next_poll, self._timers_due())
        if self._next_sync is not None:
            t = min(t, self._next_sync)
        if self._queue:
            t = min(t, self._queue[0][0])
        return t

    def _timers_due(self) -> float:
        """The earliest time a timer of the chips or of the node is due (-inf: not known)."""
        if self.chip_array is None or self.faults is not None:
            return float("-inf")
        t = self.chip_array.next_due()
        node = self.node
        if node is not None and node.powered:
            t = min(t, node.next_announce_s if node.state == ChipState.BOOT else
                    (node.next_heartbeat_s if node.next_heartbeat_s is not None else float("inf")))
        return t

    # ------------------------------------------------------------------ host -> chips
    def feed(self, data: bytes, now_s: float) -> None:
        """Serial bytes from the host."""
        self.stats.host_bytes += len(data)
        buf = self._rx
        buf += data
        while True:
            i = buf.find(b"\x00")
            if i < 0:
                if len(buf) > MAX_ENCODED_SIZE:
                    buf.clear()
                    self._rx_discard = True
                    self.stats.host_errors += 1
                    if self.node is not None:  # OVERSIZE: an integrity failure for its STATUS (§13.1)
                        self.node.rx_errors += 1
                return
            seg = bytes(buf[:i])
            del buf[:i + 1]
            if self._rx_discard:
                self._rx_discard = False
                continue
            if not seg:
                continue
            decoded = decode_frame(seg)
            self.stats.host_frames += 1
            if isinstance(decoded, DecodeError):
                self.stats.host_errors += 1
            self._from_host(seg + b"\x00", decoded, now_s)

    def receive(self, frame: CanFrame, now_s: float) -> None:
        """One CAN frame from the host (or another node on the bus)."""
        decoded = decode_can(frame.arbitration_id, frame.data, is_fd=frame.is_fd)
        self.stats.host_frames += 1
        if isinstance(decoded, DecodeError):
            self.stats.host_errors += 1
        self._from_host(frame, decoded, now_s)

    def _from_host(self, frame, decoded, now_s: float) -> None:
        """A frame from the host: the gateway node's own answer first (§13.4), then the segment —
        except a SYNC while this gateway is its segment's SYNC source (§13.3)."""
        if type(decoded) is Sync and self.sync_source:
            self.stats.syncs_refused += 1
            if self.node is not None:
                self.node.refuse_sync()
            return
        if self.node is not None:
            own = self.node.handle(frame, decoded, now_s)
            if own:
                self._emit(own, now_s)
        self._dispatch(frame, decoded, now_s)

    def _dispatch(self, frame, decoded, now_s: float) -> None:
        if type(decoded) is Sync:
            self.stats.syncs += 1
            self.sheet.record_sync(decoded.counter, now_s)
            if self.packed:
                if self.imu_format:
                    self._sync_packed_imu(frame, decoded, now_s)
                elif self.chip_array is not None:
                    self._sync_packed_array(frame, decoded, now_s)
                else:
                    self._sync_packed(frame, decoded, now_s)
                return
            if self.chip_array is not None:
                if self._late:
                    frames, owners = self.chip_array.sync(frame, decoded, now_s, self._sel, owners=True)
                    delays = self._delay_of[owners]
                    i = 0
                    while i < len(frames):  # runs of equal delay, in chip order
                        j = i + 1
                        while j < len(frames) and delays[j] == delays[i]:
                            j += 1
                        d = float(delays[i])
                        self._emit(frames[i:j], now_s + d)
                        if d:
                            self.fault_stats.late_replies += j - i
                        i = j
                else:
                    if self.faults is None:  # serial: the frames stay one byte string
                        wire = self.chip_array.sync_wire(frame, decoded, now_s, self._sel)
                        if wire is not None:
                            if wire[1]:
                                self._emit_run(wire[0], wire[1], SAMPLE_WIRE_SIZE, now_s)
                            return
                    out = self.chip_array.sync(frame, decoded, now_s, self._sel)
                    if out:
                        self._emit(out, now_s)
                return
            if self._late:
                for c, d in zip(self.chips, self.delays):
                    r = c.handle(frame, now_s, decoded)
                    if r:
                        self._emit(r, now_s + d)
                        if d:
                            self.fault_stats.late_replies += len(r)
                return
            out: list = []
            for c in self.chips:
                r = c.handle(frame, now_s, decoded)
                if r:
                    out += r
            self._emit(out, now_s)
            return
        out = []
        if self.imu_format and type(decoded) is Start:
            self._configure_imu(decoded, now_s)
        if self.chip_array is not None:
            if isinstance(decoded, Message) and decoded.node != NODE_BROADCAST:
                out = self.chip_array.handle_node(decoded.node, frame, now_s, decoded, self._sel)
            else:
                out = self.chip_array.handle(frame, now_s, decoded, self._sel)
            if out:
                self._emit(out, now_s)
            return
        if isinstance(decoded, Message) and decoded.node != NODE_BROADCAST:
            node = decoded.node
            assign = decoded.TYPE == MsgType.ASSIGN  # also heard at a BOOT chip's previous id (§3.3)
            for c in self.chips:
                if c.node == node or (assign and getattr(c, "prev_node", None) == node):
                    out += c.handle(frame, now_s, decoded)
        else:
            for c in self.chips:
                r = c.handle(frame, now_s, decoded)
                if r:
                    out += r
        if out:
            self._emit(out, now_s)

    @staticmethod
    def _is_sample(r: list) -> bool:
        return (len(r) == 1 and (isinstance(r[0], CanFrame) and len(r[0].data) == 7
                                 and (r[0].arbitration_id >> 20) & 0x3F == 3
                                 or isinstance(r[0], bytes) and len(r[0]) == SAMPLE_WIRE_SIZE))

    def _sync_packed(self, frame, sync: Sync, now_s: float) -> None:
        """Packed mode, one chip object each: the covered links' SAMPLEs into SNAPSHOT frames
        (docs §13.2). A chip whose reply delay passes `SNAPSHOT_DEADLINE_S` is sent INVALID (its
        SAMPLE is dropped); a SAMPLE of a link outside the covered runs is passed on as it is."""
        samples: list = []
        links: list[int] = []
        other: list = []
        latest = 0.0
        cov = self._cov_mask
        for c, d in zip(self.chips, self.delays):
            r = c.handle(frame, now_s, sync)
            if not r:
                continue
            link = c.link
            if link is not None and 0 <= link < cov.size and cov[link]:
                # its SAMPLE of this counter is packed; anything else it sent (a babbler's junk) passes on
                i = 0 if self._is_sample(r) else self._own_sample(r, c.node, sync.counter)
                if i is not None:
                    smp, r = r[i], r[:i] + r[i + 1:]
                    if d > SNAPSHOT_DEADLINE_S:
                        self.stats.late_dropped += 1
                    else:
                        samples.append(smp)
                        links.append(link)
                        latest = max(latest, d)
            other += r
        if samples:
            n_links = self.sheet.n_links
            counts = np.zeros((n_links, 3), dtype=np.int64)
            status = np.full(n_links, int(SampleStatus.INVALID), dtype=np.int64)
            got_c, got_s, got_l = self._decode_samples(samples, links, sync.counter)
            counts[got_l] = got_c
            status[got_l] = got_s
            frames = []
            for first, pos, m in self._chunks:
                part = self._covered[pos:pos + m]
                snap = Snapshot(self.node_id, sync.counter, first, pack_sample_words(counts[part], status[part]))
                frames.append(to_can(snap, fd=True) if self.can else encode(snap))
            self.stats.snapshots += len(frames)
            self._emit(frames, now_s + max(latest, self.flush_s))
        if other:
            self._emit(other, now_s)

    def _in_time(self, idx: np.ndarray, values: np.ndarray, link: np.ndarray):
        """§13.2: a chip answering later than SNAPSHOT_DEADLINE_S goes into the SNAPSHOT as INVALID
        (its answer dropped, counted in ``stats.late_dropped``). Returns the chips in time, their
        values and links, and the latest delay among them (0 when no chip is delayed)."""
        if not self._late:
            return idx, values, link, 0.0
        d = self._delay_of[idx]
        keep = d <= SNAPSHOT_DEADLINE_S
        self.stats.late_dropped += int((~keep).sum())
        d = d[keep]
        return idx[keep], values[keep], link[keep], (float(d.max()) if d.size else 0.0)

    def _emit_packed(self, frames: list, other: list, latest: float, now_s: float) -> None:
        """The packed frames when the latest chip in them answered (``latest`` after the SYNC), the
        other frames now; with no delay the packed frames go first, in one output. A gateway that flushes
        on a timer (`flush_s`) sends them no earlier than that after the SYNC."""
        latest = max(latest, self.flush_s)
        if frames and latest:
            self._emit(frames, now_s + latest)
        elif frames:
            other = frames + other
        if other:
            self._emit(other, now_s)

    def _sync_packed_array(self, frame, sync: Sync, now_s: float) -> None:
        """Packed mode from the chip array: the same frames as `_sync_packed`, from arrays — the
        chips' 40-bit sample words go into the SNAPSHOT as they are (a word is exactly what a
        SAMPLE carries and a SNAPSHOT packs)."""
        eng = self.chip_array
        n_links = self.sheet.n_links
        idx, word, extra = eng.sync_words(frame, sync, now_s, self._sel)
        words = self._words
        words.fill(_INVALID_WORD)  # links whose chip did not answer: INVALID, counts 0
        link = eng.link if idx.size == eng.n else eng.link[idx]
        idx, word, link, latest = self._in_time(idx, word, link)
        ok = (link >= 0) & (link < n_links)
        ok[ok] = self._cov_mask[link[ok]]  # a link outside the covered runs: passed on as a SAMPLE
        if ok.all():
            words[link] = word
            have = idx.size > 0
            other: list = []
        else:
            words[link[ok]] = word[ok]
            have = bool(ok.any())
            # samples of chips without a valid link do not go into the SNAPSHOT: as they are
            bad = idx[~ok]
            other = [(k, [f]) for k, f in zip(bad.tolist(), eng.encode(bad, sync.counter, word[~ok]))]
        # the wrapped (faulty) chips' frames, in chip order, unless it is one sample of a valid link
        for k, r in extra:
            if not r:
                continue
            lk = eng.views[k].link
            if lk is not None and 0 <= lk < n_links and self._cov_mask[lk]:
                # §13.1, §13.2: its SAMPLE is packed, whatever else it sent (a babbler's junk) passes on
                i = 0 if self._is_sample(r) else self._own_sample(r, int(eng.node[k]), sync.counter)
                if i is not None:
                    smp, r = r[i:i + 1], r[:i] + r[i + 1:]
                    d = float(self._delay_of[k])
                    if d > SNAPSHOT_DEADLINE_S:
                        self.stats.late_dropped += 1
                    else:
                        got_c, got_s, got_l = self._decode_samples(smp, [lk], sync.counter)
                        if got_l.size:
                            words[got_l] = ((got_c.astype(np.int64) & 0xFFF) @ _FIELD_SHIFT) | ((got_s & 0xF) << 36)
                            have = True
                            latest = max(latest, d)
            if r:
                other.append((k, r))
        if other:
            other.sort(key=lambda t: t[0])
            other = [f for _, r in other for f in r]
        frames: list = []
        if have:
            cov = words if self._cov_all else words[self._covered]
            cov = np.ascontiguousarray(cov, dtype="<i8")
            wb = np.ndarray((cov.shape[0],), dtype="V5", buffer=cov, strides=(8,)).tobytes()  # 5 LE bytes each
            c = sync.counter
            nid = self.node_id
            if self.can:
                frames = [to_can(Snapshot(nid, c, first, wb[5 * pos:5 * (pos + m)]), fd=True)
                          for first, pos, m in self._chunks]
            else:
                frames = [encode_frame(MsgType.SNAPSHOT, nid, _SNAP_HDR.pack(c, first, m) + wb[5 * pos:5 * (pos + m)])
                          for first, pos, m in self._chunks]
            self.stats.snapshots += len(frames)
        self._emit_packed(frames, other, latest, now_s)

    def _configure_imu(self, start: Start, now_s: float) -> None:
        """§16.5: a gateway packing IMU records configures its chips itself. Before it passes a START
        on, every chip it concerns that is still in format 0 takes CONFIG_IMU of the gateway's format at
        the default ranges (a host's own CONFIG_IMU, which passes through, has set its chips already);
        the chips' answers are the gateway's, not the host's (the chips that took it are counted in
        ``stats.imu_configured``)."""
        eng = self.chip_array
        sel = np.zeros(eng.n, dtype=bool)
        sel[self.links] = True
        if start.node != NODE_BROADCAST:
            sel &= eng.node == start.node
        sel &= eng.imu_format == 0
        for k in np.flatnonzero(sel).tolist():
            node = int(eng.node[k])
            msg = ConfigImu(node, self.imu_format)
            eng.handle_node(node, to_can(msg) if self.can else encode(msg), now_s, msg, self._sel)  # answer: ours
            self.stats.imu_configured += int(eng.imu_format[k] == self.imu_format)

    def _sync_packed_imu(self, frame, sync: Sync, now_s: float) -> None:
        """Packed mode of a 6/9-axis sheet (docs §16.5): the covered links' IMU records into
        SNAPSHOT_IMU frames, as `_sync_packed_array` packs sample words into SNAPSHOT — the same
        deadline (a later chip's link is an INVALID record), the records straight from the arrays. A
        wrapped (faulty) chip of a covered link has its record packed too and only its other frames
        passed on (§13.2); a chip in another format or without a covered link: its frames pass on as
        it sends them."""
        eng = self.chip_array
        n_links = self.sheet.n_links
        fmt = self.imu_format
        idx, recs, extra = eng.sync_records(frame, sync, now_s, fmt, self._sel)
        table = self._recs
        table[:] = self._invalid_rec
        link = eng.link if idx.size == eng.n else eng.link[idx]
        idx, recs, link, latest = self._in_time(idx, recs, link)
        ok = (link >= 0) & (link < n_links)
        ok[ok] = self._cov_mask[link[ok]]
        table[link[ok]] = recs[ok]
        have = bool(ok.any())
        other = []
        for k, r in extra:  # wrapped (faulty) chips: a covered link's record is packed too (§13.1, §13.2)
            if not r:
                continue
            lk = eng.views[k].link
            if lk is not None and 0 <= lk < n_links and self._cov_mask[lk]:
                rec, r = self._take_imu_record(r, int(eng.node[k]), sync.counter, fmt)
                if rec is not None:
                    d = float(self._delay_of[k])
                    if d > SNAPSHOT_DEADLINE_S:
                        self.stats.late_dropped += 1
                    else:
                        table[lk] = np.frombuffer(rec, dtype=np.uint8)
                        have = True
                        latest = max(latest, d)
            if r:
                other.append((k, r))
        if not ok.all():  # records of chips without a covered link: as IMU_SAMPLEs of their own
            c_, s_, t_, g_, m_ = unpack_imu_records(recs[~ok].tobytes(), fmt)
            for j, k in enumerate(idx[~ok].tolist()):
                mag = (None,) * 3 if m_ is None else tuple(int(v) for v in m_[j])
                msg = ImuSample(int(eng.node[k]), sync.counter, *(int(v) for v in c_[j]), int(s_[j]), int(t_[j]),
                                *(int(v) for v in g_[j]), *mag)
                other.append((k, imu_can_frames(msg, fd=self.fd) if self.can else [encode(msg)]))
            other.sort(key=lambda t: t[0])
        other = [f for _, r in other for f in r]
        frames: list = []
        if have:
            c, nid = sync.counter, self.node_id
            rows = table if self._cov_all else table[self._covered]
            if self.can:
                frames = [to_can(SnapshotImu(nid, c, first, fmt, rows[pos:pos + m].tobytes()), fd=True)
                          for first, pos, m in self._imu_chunks]
            else:
                frames = [encode_frame(MsgType.SNAPSHOT_IMU, nid, _SNAP_IMU_HDR.pack(c, first, m, fmt)
                                       + rows[pos:pos + m].tobytes()) for first, pos, m in self._imu_chunks]
            self.stats.snapshots += len(frames)
        self._emit_packed(frames, other, latest, now_s)

    def _decode_one(self, f):
        if self.can:
            return decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) if isinstance(f, CanFrame) else None
        return decode_frame(f[:-1]) if isinstance(f, (bytes, bytearray)) and f[-1:] == b"\0" else None

    def _own_sample(self, frames: list, node: int, counter: int) -> int | None:
        """Where among what one chip sent after a SYNC is its SAMPLE of ``counter`` (None: not there)."""
        for i, f in enumerate(frames):
            m = self._decode_one(f)
            if isinstance(m, Sample) and m.node == node and m.counter == counter:
                return i
        return None

    def _take_imu_record(self, frames: list, node: int, counter: int, fmt: int) -> tuple[bytes | None, list]:
        """§13.1 forwarding, §16.5 packing, for what one wrapped (faulty) chip sent after a SYNC: its record
        of ``counter`` in format ``fmt`` — an IMU_SAMPLE (serial, CAN FD), or on classic CAN its IMU_GYRO
        (+ IMU_MAG) + IMU_ACCEL frames — is taken for the SNAPSHOT_IMU; every other frame (a babbler's
        junk, a STATUS, a record of another format or counter) is passed on unchanged, in order.
        Returns ``(record bytes or None, the frames to pass on)``."""
        msgs = [self._decode_one(f) for f in frames]
        mine = [isinstance(m, Message) and m.node == node for m in msgs]
        for i, m in enumerate(msgs):
            if not mine[i]:
                continue
            if isinstance(m, ImuSample) and m.counter == counter and m.format == fmt:
                return m.record(), frames[:i] + frames[i + 1:]
            if isinstance(m, ImuGyro) and m.counter == counter:  # classic CAN: the frames of §16.4, in order
                want = [ImuMag, ImuAccel] if fmt == SampleFormat.IMU9 else [ImuAccel]
                rest = [j for j in range(i + 1, len(msgs)) if mine[j]][:len(want)]
                parts = [msgs[j] for j in rest]
                if (len(parts) == len(want) and all(type(p) is w for p, w in zip(parts, want))
                        and all(p.counter == counter for p in parts[:-1]) and parts[-1].counter_lo == counter & 0xFF):
                    a, mag = parts[-1], (parts[0].mx, parts[0].my, parts[0].mz) if len(parts) == 2 else (None,) * 3
                    rec = ImuSample(node, counter, a.x, a.y, a.z, a.status, a.time_us, m.gx, m.gy, m.gz, *mag).record()
                    taken = {i, *rest}
                    return rec, [f for j, f in enumerate(frames) if j not in taken]
        return None, frames

    def _decode_samples(self, samples: list, links: list[int], counter: int):
        links_a = np.asarray(links, dtype=np.int64)
        if self.can:
            data = np.frombuffer(b"".join(f.data for f in samples), dtype=np.uint8).reshape(-1, 7)
            ctr = data[:, 0].astype(np.int64) | (data[:, 1].astype(np.int64) << 8)
            from protocol.messages import unpack_sample_words
            counts, status = unpack_sample_words(np.ascontiguousarray(data[:, 2:]).ravel())
        else:
            ev = self._snap_decoder.feed(b"".join(samples))
            if len(ev) != 1 or len(ev[0]) != len(samples):  # something did not decode: slow path
                keep = []
                for i, f in enumerate(samples):
                    m = decode_frame(f[:-1])
                    if not isinstance(m, DecodeError):
                        keep.append((i, m))
                idx = np.asarray([i for i, _ in keep], dtype=np.int64)
                ms = [m for _, m in keep]
                ctr = np.asarray([m.counter for m in ms], dtype=np.int64)
                counts = np.asarray([(m.x, m.y, m.z) for m in ms], dtype=np.int64).reshape(-1, 3)
                status = np.asarray([m.status for m in ms], dtype=np.int64)
                links_a = links_a[idx]
            else:
                b = ev[0]
                ctr, counts, status = b.counter.astype(np.int64), b.counts, b.status
        ok = ctr == counter
        return counts[ok], status[ok].astype(np.int64), links_a[ok]

    # ------------------------------------------------------------------ chips -> host
    def _emit(self, frames: list, due_s: float) -> None:
        self.stats.chip_frames += len(frames)
        if self.faults is not None:
            self._queue.extend(self.faults.process(frames, due_s))
        else:
            self._queue.extend((due_s, f) for f in frames)
        if self._late or self.flush_s or (self.faults is not None and (self.spec.delay_ms or self.spec.jitter_ms)):
            self._queue.sort(key=lambda p: p[0])  # stable: FIFO among equal times

    def _emit_run(self, data: bytes, n: int, size: int, due_s: float) -> None:
        """``n`` frames of ``size`` bytes back to back (no stream faults: those act per frame)."""
        self.stats.chip_frames += n
        self._queue.append((due_s, _Run(data, n, size)))
        self._runs += 1
        if self._late:
            self._queue.sort(key=lambda p: p[0])

    def _take(self, now_s: float) -> list:
        """The queue entries due by ``now_s``, removed from the queue."""
        q = self._queue
        if not q:
            return []
        if q[-1][0] <= now_s:
            self._queue = []
            return q
        n = 0
        while n < len(q) and q[n][0] <= now_s:
            n += 1
        out = q[:n]
        del q[:n]
        return out

    def pop_output(self, now_s: float) -> list:
        """Frames due by ``now_s``, in wire order: serial bytes, `CanFrame`, or `ERROR_FRAME`."""
        items = self._take(now_s)
        if not items:
            return []
        if self._runs:
            out: list = []
            for _, f in items:
                if type(f) is _Run:
                    out += f.frames()
                    self._runs -= 1
                else:
                    out.append(f)
        else:
            out = [f for _, f in items]
        self.stats.frames_to_host += len(out)
        return out

    def pop_wire(self, now_s: float) -> tuple[bytes, int]:
        """Serial: the frames due by ``now_s`` back to back, and how many (`pop_output` joined,
        without a Python object per frame)."""
        items = self._take(now_s)
        if not items:
            return b"", 0
        parts = []
        n = 0
        for _, f in items:
            if type(f) is _Run:
                parts.append(f.data)
                n += f.n
                self._runs -= 1
            else:
                parts.append(f)
                n += 1
        self.stats.frames_to_host += n
        return b"".join(parts), n

    def commission(self, now_s: float, *, start: bool = True, first_node: int = 1) -> None:
        """Assign every chip behind this gateway node ``first_node + link`` and its physical link
        (the sheet's layout), and START them, through real frames; the gateway node (if it is one)
        gets node ``0x7FFF - stream``; the answers are discarded. A shortcut for tests and
        benchmarks: a host normally does this."""
        from protocol.messages import Start
        saved, self._queue = self._queue, []
        saved_runs, self._runs = self._runs, 0
        faults, self.faults = self.faults, None  # discarded answers: no fault is injected or counted
        for k, c in zip(self.links, self.chips):
            msg = Assign(c.node, new_node=first_node + k, link=k, uid_low=c.uid & 0xFFFFFFFF)
            self._inject(msg, now_s)
        if self.node is not None and self.node.state == ChipState.BOOT:  # the gateway too (§13.1)
            msg = Assign(self.node.node, new_node=0x7FFF - self.stream, link=LINK_NONE, uid_low=self.uid & 0xFFFFFFFF)
            self.node.handle(to_can(msg) if self.can else encode(msg), msg, now_s)
        if start:
            self._inject(Start(0), now_s)
        self._queue, self._runs, self.faults = saved, saved_runs, faults

    def _inject(self, msg: Message, now_s: float) -> None:
        frame = to_can(msg) if self.can else encode(msg)
        self._dispatch(frame, msg, now_s)

    def pop_bytes(self, now_s: float) -> bytes:
        """Serial: the due frames as one byte string."""
        return self.pop_wire(now_s)[0]


assert ERROR_FRAME  # re-exported for CAN devices
