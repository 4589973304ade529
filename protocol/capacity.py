"""How many chips fit one bus, from the frame sizes of this protocol (docs/protocol.md §10).

Bit counts follow ISO 11898-1: a classic extended data frame is 64 + 8·n bits before stuffing
(SOF 1, id 11, SRR 1, IDE 1, id 18, RTR 1, r1 r0 2, DLC 4, data 8n, CRC 15, CRC-del 1, ACK 2,
EOF 7) + 3 bits interframe space = 67 + 8·n; worst-case stuffing adds one bit per four after the first
over the 54 + 8n stuffed bits (SOF..CRC). CAN FD: the arbitration phase runs at the nominal rate,
the data phase (ESI, DLC, data, stuff count, CRC-17/21 with fixed stuff bits) at the data rate.
UART 8N1: 10 bits per byte.

>>> classic_can_frame_bits(8)
(131, 160)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .can import FD_LENGTHS, MAX_FD_IMU_RECORDS, MAX_FD_SNAPSHOT_SAMPLES, fd_length
from .framing import CRC_SIZE, HEADER_SIZE, MAX_PAYLOAD_SIZE, SAMPLE_WIRE_SIZE, cobs_encoded_size
from .messages import IMU_RECORD_SIZE, MAX_SERIAL_IMU_RECORDS, SAMPLE_WORD_SIZE, Sample, SampleFormat, Snapshot, SnapshotImu

__all__ = ["classic_can_frame_bits", "fd_can_frame_time_s", "serial_snapshot_bytes", "Capacity",
           "capacity_table", "MAX_SERIAL_SNAPSHOT_SAMPLES", "bus_load", "buses_needed", "serial_snapshot_imu_bytes",
           "imu_capacity_rows"]

#: SNAPSHOT samples per serial frame: (1018 - 5) // 5
MAX_SERIAL_SNAPSHOT_SAMPLES = (MAX_PAYLOAD_SIZE - Snapshot.HEADER_SIZE) // SAMPLE_WORD_SIZE
assert MAX_SERIAL_SNAPSHOT_SAMPLES == 202


def classic_can_frame_bits(n_data: int) -> tuple[int, int]:
    """(best, worst) bits on the bus of one classic extended frame with ``n_data`` bytes, incl. IFS."""
    if not 0 <= n_data <= 8:
        raise ValueError(f"Invalid classic CAN length: {n_data}")
    base = 67 + 8 * n_data  # 64 + 8n frame bits + 3 bits IFS
    stuffed = 54 + 8 * n_data
    return base, base + (stuffed - 1) // 4


def fd_can_frame_time_s(n_data: int, nominal_bps: float = 1e6, data_bps: float = 8e6) -> tuple[float, float]:
    """(best, worst) seconds of one CAN FD extended frame with bit-rate switch, incl. IFS."""
    n = fd_length(n_data)
    arb = 1 + 11 + 1 + 1 + 18 + 1 + 1 + 1  # SOF, base id, SRR, IDE, ext id, RRS, FDF, res
    arb_tail = 1 + 2 + 7 + 3  # CRC delimiter (nominal after switch back), ACK, EOF, IFS
    crc = 17 if n <= 16 else 21
    fixed_stuff = math.ceil((4 + crc) / 4)  # fixed stuff bits in stuff count + CRC field
    data = 1 + 1 + 4 + 8 * n + 4 + crc + fixed_stuff  # BRS, ESI, DLC, data, stuff count, CRC
    arb_worst = arb + (arb - 1) // 4
    data_worst = data + (1 + 1 + 4 + 8 * n) // 4
    best = (arb + arb_tail) / nominal_bps + data / data_bps
    worst = (arb_worst + arb_tail) / nominal_bps + data_worst / data_bps
    return best, worst


def serial_snapshot_bytes(n_links: int) -> int:
    """Bytes on the wire (COBS + delimiters) of one whole snapshot of ``n_links`` samples."""
    total, left = 0, n_links
    while left > 0:
        k = min(left, MAX_SERIAL_SNAPSHOT_SAMPLES)
        total += cobs_encoded_size(HEADER_SIZE + Snapshot.HEADER_SIZE + SAMPLE_WORD_SIZE * k + CRC_SIZE) + 1
        left -= k
    return total


def serial_snapshot_imu_bytes(n_links: int, fmt: int) -> int:
    """Bytes on the wire of one whole snapshot of ``n_links`` IMU records packed in SNAPSHOT_IMU (§16.5)."""
    size, cap = IMU_RECORD_SIZE[SampleFormat(fmt)], MAX_SERIAL_IMU_RECORDS[SampleFormat(fmt)]
    total, left = 0, n_links
    while left > 0:
        k = min(left, cap)
        total += cobs_encoded_size(HEADER_SIZE + SnapshotImu.HEADER_SIZE + size * k + CRC_SIZE) + 1
        left -= k
    return total


@dataclass(frozen=True)
class Capacity:
    link: str
    carries: str
    frame: str
    frames_per_s: tuple[float, float]  #: (worst, best)
    chips_at_rate: tuple[int, int]  #: (worst, best) chips per bus at `rate_hz`


def capacity_table(rate_hz: float = 145.0) -> list[Capacity]:
    """Chips per bus at ``rate_hz`` for each transport and message (the table of docs §10)."""
    if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need a finite value > 0)")
    rows = []
    best, worst = classic_can_frame_bits(Sample.SIZE)
    f = (1e6 / worst, 1e6 / best)
    rows.append(Capacity("classic CAN 1 Mbit/s, 29-bit id", "SAMPLE (7 B)", f"{best}-{worst} bits",
                         f, (int(f[0] / rate_hz), int(f[1] / rate_hz))))
    n = Snapshot.HEADER_SIZE + SAMPLE_WORD_SIZE * MAX_FD_SNAPSHOT_SAMPLES
    tb, tw = fd_can_frame_time_s(n)
    f = (1 / tw, 1 / tb)
    rows.append(Capacity("CAN FD 1/8 Mbit/s", f"SNAPSHOT, {MAX_FD_SNAPSHOT_SAMPLES} samples ({fd_length(n)} B)",
                         f"{tb * 1e6:.0f}-{tw * 1e6:.0f} µs", f,
                         (int(f[0] * MAX_FD_SNAPSHOT_SAMPLES / rate_hz), int(f[1] * MAX_FD_SNAPSHOT_SAMPLES / rate_hz))))
    tb, tw = fd_can_frame_time_s(Sample.SIZE)
    f = (1 / tw, 1 / tb)
    rows.append(Capacity("CAN FD 1/8 Mbit/s", "SAMPLE (7 B)", f"{tb * 1e6:.0f}-{tw * 1e6:.0f} µs", f,
                         (int(f[0] / rate_hz), int(f[1] / rate_hz))))
    for baud in (3_000_000, 12_000_000):
        fps = baud / 10 / SAMPLE_WIRE_SIZE
        rows.append(Capacity(f"UART 8N1 {baud // 1_000_000} Mbaud", "SAMPLE per chip", f"{SAMPLE_WIRE_SIZE} B",
                             (fps, fps), (int(fps / rate_hz),) * 2))
        # packed: largest n whose snapshot fits the byte budget at rate_hz (SYNC from the gateway, no host SYNC bytes)
        budget = baud / 10 / rate_hz
        lo, hi = 1, 100_000
        while lo < hi:
            mid = (lo + hi + 1) // 2
            lo, hi = (mid, hi) if serial_snapshot_bytes(mid) <= budget else (lo, mid - 1)
        rows.append(Capacity(f"UART 8N1 {baud // 1_000_000} Mbaud", "SNAPSHOT (packed)",
                             f"{serial_snapshot_bytes(lo)} B per snapshot", (rate_hz, rate_hz), (lo, lo)))
    return rows + imu_capacity_rows(rate_hz)


def imu_capacity_rows(rate_hz: float = 145.0) -> list[Capacity]:
    """The IMU formats (docs §16, new in 1.2): per chip on classic CAN (2 or 3 frames of 8 bytes), CAN FD
    (one IMU_SAMPLE of 16 or 24 bytes), UART (IMU_SAMPLE); packed in SNAPSHOT_IMU on CAN FD and UART."""
    rows = []
    for fmt, name, n_frames in ((SampleFormat.IMU6, "6-axis", 2), (SampleFormat.IMU9, "9-axis", 3)):
        size = IMU_RECORD_SIZE[fmt]
        best, worst = classic_can_frame_bits(8)
        f = (1e6 / (n_frames * worst), 1e6 / (n_frames * best))  # records per second
        parts = "IMU_GYRO + IMU_ACCEL" if n_frames == 2 else "IMU_GYRO + IMU_MAG + IMU_ACCEL"
        rows.append(Capacity("classic CAN 1 Mbit/s, 29-bit id", f"{name}: {parts} ({n_frames} × 8 B)",
                             f"{n_frames * best}-{n_frames * worst} bits", f, (int(f[0] / rate_hz), int(f[1] / rate_hz))))
        tb, tw = fd_can_frame_time_s(2 + size)
        f = (1 / tw, 1 / tb)
        rows.append(Capacity("CAN FD 1/8 Mbit/s", f"{name}: IMU_SAMPLE ({fd_length(2 + size)} B)",
                             f"{tb * 1e6:.0f}-{tw * 1e6:.0f} µs", f, (int(f[0] / rate_hz), int(f[1] / rate_hz))))
        k = MAX_FD_IMU_RECORDS[fmt]
        tb, tw = fd_can_frame_time_s(SnapshotImu.HEADER_SIZE + size * k)
        f = (1 / tw, 1 / tb)
        rows.append(Capacity("CAN FD 1/8 Mbit/s", f"{name}: SNAPSHOT_IMU, {k} records (64 B)",
                             f"{tb * 1e6:.0f}-{tw * 1e6:.0f} µs", f, (int(f[0] * k / rate_hz), int(f[1] * k / rate_hz))))
        wire = cobs_encoded_size(HEADER_SIZE + 2 + size + CRC_SIZE) + 1
        for baud in (3_000_000, 12_000_000):
            fps = baud / 10 / wire
            rows.append(Capacity(f"UART 8N1 {baud // 1_000_000} Mbaud", f"{name}: IMU_SAMPLE per chip", f"{wire} B",
                                 (fps, fps), (int(fps / rate_hz),) * 2))
            budget = baud / 10 / rate_hz
            lo, hi = 1, 100_000
            while lo < hi:
                mid = (lo + hi + 1) // 2
                lo, hi = (mid, hi) if serial_snapshot_imu_bytes(mid, fmt) <= budget else (lo, mid - 1)
            rows.append(Capacity(f"UART 8N1 {baud // 1_000_000} Mbaud", f"{name}: SNAPSHOT_IMU (packed)",
                                 f"{serial_snapshot_imu_bytes(lo, fmt)} B per snapshot", (rate_hz, rate_hz), (lo, lo)))
    return rows


def bus_load(n_chips: int, rate_hz: float, *, kind: str, bitrate: float, fd: bool = False,
             data_bitrate: float | None = None, packed: bool = False, fmt: int = 0) -> float:
    """Worst-case fraction of a bus's time that ``n_chips`` sampled at ``rate_hz`` take (1.0 = full).

    ``kind="serial"``: a UART at ``bitrate`` baud, 8N1 (the chip-to-host direction; SYNC goes the
    other way). ``kind="can"``: classic CAN at ``bitrate`` (or CAN FD with ``data_bitrate``), one
    SYNC per period included. ``packed``: the gateway sends SNAPSHOT frames (serial, or CAN FD);
    classic CAN cannot pack, so per-chip SAMPLE is counted there. ``fmt`` 1 or 2: 6/9-axis IMU records
    (docs §16: IMU_SAMPLE per chip, or on classic CAN its 2 or 3 frames; SNAPSHOT_IMU packed).

    >>> round(bus_load(21, 145, kind="can", bitrate=1e6, fmt=1), 2)   # (21 x 2 x 160 + 100) x 145 / 1e6
    0.99

    >>> round(bus_load(364, 100, kind="can", bitrate=1e6), 2)  # 364 x 100 x 150 bits + 100 x 100 (SYNC)
    5.47
    >>> round(bus_load(50, 145, kind="can", bitrate=1e6), 2)   # (50 x 150 + 100) x 145 / 1e6
    1.1
    >>> round(bus_load(364, 145, kind="serial", bitrate=12e6), 2)      # per-chip on 12 Mbaud
    0.66
    """
    if not (isinstance(n_chips, int) and n_chips >= 0):
        raise ValueError(f"Invalid n_chips: {n_chips!r} (need an integer >= 0)")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need a finite value > 0)")
    if not (math.isfinite(bitrate) and bitrate > 0):
        raise ValueError(f"Invalid bitrate: {bitrate!r} (need a finite value > 0)")
    if fmt not in (0, 1, 2):
        raise ValueError(f"Invalid fmt: {fmt!r} (0 SAMPLE, 1 6-axis, 2 9-axis records)")
    if fmt:
        return _imu_load(n_chips, rate_hz, kind, bitrate, fd, data_bitrate, packed, SampleFormat(fmt))
    if kind == "serial":
        per_period = serial_snapshot_bytes(n_chips) if packed else n_chips * SAMPLE_WIRE_SIZE
        return rate_hz * per_period * 10 / bitrate
    if kind != "can":
        raise ValueError(f"Invalid kind: {kind!r} (need 'serial' or 'can')")
    sync_bits = classic_can_frame_bits(2)[1]
    if not fd:
        return rate_hz * (n_chips * classic_can_frame_bits(Sample.SIZE)[1] + sync_bits) / bitrate
    data_bps = data_bitrate if data_bitrate is not None else 8 * bitrate
    if packed:
        full, rest = divmod(n_chips, MAX_FD_SNAPSHOT_SAMPLES)
        t = full * fd_can_frame_time_s(Snapshot.HEADER_SIZE + SAMPLE_WORD_SIZE * MAX_FD_SNAPSHOT_SAMPLES,
                                       bitrate, data_bps)[1]
        if rest:
            t += fd_can_frame_time_s(Snapshot.HEADER_SIZE + SAMPLE_WORD_SIZE * rest, bitrate, data_bps)[1]
    else:
        t = n_chips * fd_can_frame_time_s(Sample.SIZE, bitrate, data_bps)[1]
    return rate_hz * (t + sync_bits / bitrate)


def _imu_load(n, rate_hz, kind, bitrate, fd, data_bitrate, packed, fmt) -> float:
    size = IMU_RECORD_SIZE[fmt]
    if kind == "serial":
        per_period = (serial_snapshot_imu_bytes(n, fmt) if packed
                      else n * (cobs_encoded_size(HEADER_SIZE + 2 + size + CRC_SIZE) + 1))
        return rate_hz * per_period * 10 / bitrate
    if kind != "can":
        raise ValueError(f"Invalid kind: {kind!r} (need 'serial' or 'can')")
    sync_bits = classic_can_frame_bits(2)[1]
    if not fd:
        frames = 2 if fmt == SampleFormat.IMU6 else 3
        return rate_hz * (n * frames * classic_can_frame_bits(8)[1] + sync_bits) / bitrate
    data_bps = data_bitrate if data_bitrate is not None else 8 * bitrate
    if packed:
        k = MAX_FD_IMU_RECORDS[fmt]
        full, rest = divmod(n, k)
        t = full * fd_can_frame_time_s(SnapshotImu.HEADER_SIZE + size * k, bitrate, data_bps)[1]
        if rest:
            t += fd_can_frame_time_s(SnapshotImu.HEADER_SIZE + size * rest, bitrate, data_bps)[1]
    else:
        t = n * fd_can_frame_time_s(2 + size, bitrate, data_bps)[1]
    return rate_hz * (t + sync_bits / bitrate)


def buses_needed(n_links: int, rate_hz: float = 145.0) -> list[tuple[Capacity, int]]:
    """For each row of `capacity_table`: how many such buses a sheet of ``n_links`` chips needs
    (from the worst-case chips per bus; 0 chips per bus at this rate -> no number of buses helps: -1).

    >>> [(c.link, c.carries, k) for c, k in buses_needed(364, 145.0)][0]   # 45 chips per bus: ceil(364 / 45)
    ('classic CAN 1 Mbit/s, 29-bit id', 'SAMPLE (7 B)', 9)
    """
    if not (isinstance(n_links, int) and n_links >= 1):
        raise ValueError(f"Invalid n_links: {n_links!r} (need an integer >= 1)")
    out = []
    for row in capacity_table(rate_hz):
        per = row.chips_at_rate[0]
        out.append((row, math.ceil(n_links / per) if per > 0 else -1))
    return out


assert FD_LENGTHS[-1] == 64
