"""Every reader of untrusted files, fuzzed (hypothesis, bounded: few examples, no deadline): a
mutated real recording, layout, calibration, robot config or CAN log is read or refused with the
ValueError the reader documents — never another exception, never an allocation beyond the bounds
(peak of Python allocations measured with tracemalloc)."""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

FUZZ = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_CACHE: dict = {}


def _base(tmp_path_factory) -> dict:
    """A real recording, layout, calibration, robot config and CAN log, made once."""
    if not _CACHE:
        from host.analysis.calibration import Calibration
        from tests.host.record.crafted import base_recording

        d = tmp_path_factory.mktemp("fuzz-base")
        _CACHE["mcap"] = base_recording(d / "run.mcap", n=6).read_bytes()
        _CACHE["layout_csv"] = "uid,link\n" + "".join(f"0x{k + 1:016X},{k}\n" for k in range(12))
        _CACHE["layout_json"] = json.dumps({"format": "capsheet-layout", "version": 1, "rows": 3, "cols": 3,
                                            "chips": [{"uid": f"0x{k + 1:X}", "link": k} for k in range(12)]})
        _CACHE["cal"] = json.dumps(Calibration.identity(3, 3).to_dict())
        _CACHE["robot"] = ('[view]\nframe = "base"\nrate = 20\n[[sheet]]\nname = "a"\ntranslation = [0.1, 0, 0]\n'
                           'rotation = [0, 0, 0, 1]\n[[sheet]]\nname = "b"\ntranslation = [0, 0.2, 0]\n'
                           'rpy_deg = [0, 90, 0]\n')
        _CACHE["canlog"] = "".join(f"({1.0 + k / 100:.6f}) can0 {0x1000 + k:08X}#{k:02X}00FF10\n" for k in range(30))
    return _CACHE


def _mutate(data: bytes, edits) -> bytes:
    b = bytearray(data)
    for pos, chunk, delete in edits:
        if not b:
            break
        at = pos % len(b)
        b[at:at + delete] = chunk
    return bytes(b)


edits = st.lists(st.tuples(st.integers(0, 1 << 20), st.binary(max_size=12), st.integers(0, 12)), min_size=1,
                 max_size=4)


def _bounded(fn, limit_mb: float):
    """``fn()``'s ValueError, or None; fails on any other exception or a peak above ``limit_mb``."""
    tracemalloc.start()
    try:
        fn()
        err = None
    except ValueError as exc:
        err = exc
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak < limit_mb * 1e6, f"peak {peak / 1e6:.1f} MB"
    if err is not None:
        assert "\n" not in str(err), str(err)
    return err


@pytest.fixture
def base(tmp_path_factory):
    """Makes the base files once (`_base`); the tests read them from `_CACHE` (hypothesis would print
    a fixture's whole value with every failing example)."""
    _base(tmp_path_factory)


@FUZZ
@given(edits)
def test_a_mutated_recording_is_read_or_refused(base, tmp_path, e):
    from host.record.recording import iter_snapshots, read

    p = tmp_path / "m.mcap"
    p.write_bytes(_mutate(_CACHE["mcap"], e))
    _bounded(lambda: read(p), 80)
    _bounded(lambda: [len(b) for b in iter_snapshots(p, 4)], 80)


@FUZZ
@given(edits, st.sampled_from(["layout_csv", "layout_json"]))
def test_a_mutated_layout_is_read_or_refused(base, tmp_path, e, kind):
    from protocol.layout import LayoutError, load_layout

    p = tmp_path / ("l.csv" if kind == "layout_csv" else "l.json")
    p.write_bytes(_mutate(_CACHE[kind].encode(), e))
    err = _bounded(lambda: load_layout(p), 20)
    assert err is None or isinstance(err, LayoutError)


@FUZZ
@given(edits)
def test_a_mutated_calibration_is_read_or_refused(base, tmp_path, e):
    from host.analysis.calibration import Calibration

    p = tmp_path / "c.json"
    p.write_bytes(_mutate(_CACHE["cal"].encode(), e))
    _bounded(lambda: Calibration.load(p), 20)


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                                      max_size=4), max_leaves=12)


@FUZZ
@given(st.sampled_from(["rows", "cols", "chips", "bias", "scale", "misalignment", "reference_sensitivity",
                        "pose_directions", "outliers", "link"]), json_values)
def test_a_calibration_with_any_value_in_any_field_is_read_or_refused(base, key, value):
    from host.analysis.calibration import Calibration

    doc = json.loads(_CACHE["cal"])
    if key in ("rows", "cols", "chips", "pose_directions", "outliers"):
        doc[key] = value
    else:
        doc["chips"][3][key] = value
    _bounded(lambda: Calibration.from_dict(doc, "fuzzed"), 20)


@FUZZ
@given(edits)
def test_a_mutated_robot_config_is_read_or_refused(base, tmp_path, e):
    from host.publish.robot import load_robot

    p = tmp_path / "r.toml"
    p.write_bytes(_mutate(_CACHE["robot"].encode(), e))
    _bounded(lambda: load_robot(p), 20)


@FUZZ
@given(edits)
def test_a_mutated_can_log_is_read_or_refused(base, tmp_path, e):
    from host.record.replay import load_can_log

    p = tmp_path / "c.log"
    p.write_bytes(_mutate(_CACHE["canlog"].encode(), e))
    _bounded(lambda: load_can_log(p), 20)


@FUZZ
@given(st.text(max_size=200) | st.binary(max_size=200))
def test_any_text_is_json_or_refused(raw):
    from protocol.files import loads_json
    _bounded(lambda: loads_json(raw, "x"), 5)


@FUZZ
@given(st.text(max_size=200))
def test_any_text_is_toml_or_refused(raw):
    from protocol.files import loads_toml
    _bounded(lambda: loads_toml(raw, "x"), 5)


def test_the_fuzzed_recording_is_read_whole_before_mutation(base, tmp_path):
    """The base the recording fuzzer mutates is a real recording, read whole (not refused)."""
    from host.record.recording import read
    p = tmp_path / "ok.mcap"
    p.write_bytes(_CACHE["mcap"])
    r = read(p)
    assert len(r) == 6 and not r.truncated
    Path(p).unlink()


def test_every_61st_byte_of_a_real_recording_flipped_is_read_or_refused(base, tmp_path):
    """A bounded mutation loop over a real file: each of ~130 copies with one byte inverted is read
    or refused with one line. (Before the bounded reader, the same loop met ZstdError, DecodeError,
    MemoryError and OverflowError tracebacks.)"""
    from host.record.recording import iter_snapshots, read

    data = _CACHE["mcap"]
    p = tmp_path / "flip.mcap"
    outcomes = {"read": 0, "refused": 0}
    for pos in range(0, len(data), 61):
        b = bytearray(data)
        b[pos] ^= 0xFF
        p.write_bytes(bytes(b))
        for fn in (lambda: read(p), lambda: list(iter_snapshots(p, 4))):
            outcomes["refused" if _bounded(fn, 80) is not None else "read"] += 1
    assert outcomes["refused"] > 0 and outcomes["read"] > 0, outcomes  # both kinds of copies met
