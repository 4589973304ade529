"""Recordings in MCAP (docs/recording.md): the one import path for writing and reading them.

What a session receives, aggregates and estimates, in a file Foxglove opens: the wire input of every
transport, the SYNCs, the snapshots, the estimates, contacts and the 3D scene. The work is split by
concern — the channels both sides share (`host.record.channels`), the writer
(`host.record.writer`: `Recorder`), the reader (`host.record.reader`: `read`, `iter_snapshots`) —
and their public names are here, where every command and tool imports them from.
"""

from __future__ import annotations

from host.record.channels import (FORMAT, HOST_CALIBRATION, SCHEMAS, TOPIC_CONTACTS, TOPIC_ESTIMATE, TOPIC_IMU,
                                  TOPIC_RAW, TOPIC_SNAPSHOT, TOPIC_SYNC, packed_float, packed_sint32,
                                  recording_set, split_path, versions)
from host.record.reader import Recording, SnapshotBatch, iter_snapshots, read, read_recording, snapshot_count
from host.record.writer import (COMPRESSION_LEVEL, COMPRESSION_LEVEL_LARGE, ESTIMATE_FILE_PERIOD_S,
                                SCENE_FILE_PERIOD_S, Recorder, compression_level_for, tap_transport)

#: a recording of a sheet of more than this many links (with no live view) is written by a process
#: of its own (`open_recorder`; the same as `host.record.writer.LARGE_SHEET_LINKS`)
PROCESS_WRITER_LINKS = 2048


def open_recorder(path, lattice, link_length: float, *, process: bool | None = None, **kwargs):
    """The recorder a session writes with: a `Recorder` in this process, or a
    `host.record.writer_process.RecorderProcess` (the same file, written by a process of its own,
    docs/recording.md "A writer process") for a file without a live view (a live view shares this
    process's context: written here). ``process`` None: the process for a sheet of more than
    `PROCESS_WRITER_LINKS` links (a 64x64 sheet's recording spent
    ~0.4-0.9 ms of the receive path's interpreter lock per SYNC; here ~0.15 ms of pipe writes)."""
    alone = path is not None and kwargs.get("live_port") is None  # a live view shares this process's writer
    if process is None:
        process = lattice.n_links > PROCESS_WRITER_LINKS
    if process and alone:
        from host.record.writer_process import RecorderProcess
        return RecorderProcess(path, lattice, link_length, **kwargs)
    return Recorder(path, lattice, link_length, **kwargs)


__all__ = ["Recorder", "open_recorder", "PROCESS_WRITER_LINKS", "Recording", "read", "read_recording", "iter_snapshots", "SnapshotBatch", "snapshot_count",
           "tap_transport", "versions", "compression_level_for", "recording_set", "split_path",
           "packed_sint32", "packed_float", "SCHEMAS", "HOST_CALIBRATION",
           "COMPRESSION_LEVEL", "COMPRESSION_LEVEL_LARGE", "ESTIMATE_FILE_PERIOD_S", "SCENE_FILE_PERIOD_S",
           "TOPIC_RAW", "TOPIC_SYNC", "TOPIC_SNAPSHOT", "TOPIC_ESTIMATE", "TOPIC_CONTACTS", "TOPIC_IMU",
           "FORMAT"]
