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

__all__ = ["Recorder", "Recording", "read", "read_recording", "iter_snapshots", "SnapshotBatch", "snapshot_count",
           "tap_transport", "versions", "compression_level_for", "recording_set", "split_path",
           "packed_sint32", "packed_float", "SCHEMAS", "HOST_CALIBRATION",
           "COMPRESSION_LEVEL", "COMPRESSION_LEVEL_LARGE", "ESTIMATE_FILE_PERIOD_S", "SCENE_FILE_PERIOD_S",
           "TOPIC_RAW", "TOPIC_SYNC", "TOPIC_SNAPSHOT", "TOPIC_ESTIMATE", "TOPIC_CONTACTS", "TOPIC_IMU",
           "FORMAT"]
