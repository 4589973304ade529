"""Any bytes into the payload readers (host/publish/zenoh_pub.py) and an estimate worker's sheet
(host/workers/distribute.py) never raise anything but the ValueError they document, and never
allocate more than the payload implies. Hypothesis, bounded (few examples, no deadline)."""

from __future__ import annotations

import struct
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.publish.zenoh_pub import (HEADER, KINDS, check_lattice, decode_estimate, decode_info,
                                    decode_snapshot, encode_snapshot)
from host.workers.distribute import SheetWork

FUZZ = settings(max_examples=60, deadline=None, derandomize=True)
check_lattice(2, 2)  # its lazy import done now, not inside a measured call


def _headers():
    """A header that passes the magic and version checks, everything else arbitrary."""
    return st.builds(lambda kind, flags, rows, cols, n, counter, ts, wall: HEADER.pack(
        KINDS[kind], 1, flags, rows, cols, n, 0, counter, ts, wall),
        st.sampled_from(sorted(KINDS)), st.integers(0, 255), st.integers(0, 65535), st.integers(0, 65535),
        st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1), st.floats(), st.floats())


payloads = st.one_of(st.binary(max_size=300), st.tuples(_headers(), st.binary(max_size=2000)).map(b"".join))


@FUZZ
@given(payloads)
def test_any_bytes_decode_or_raise_value_error_without_allocating_for_the_header(payload):
    tracemalloc.start()
    try:
        for decode in (decode_snapshot, decode_estimate):
            try:
                out = decode(payload)
            except ValueError:
                continue
            # decoded: the lattice is one --lattice takes and the arrays are exactly the payload's
            check_lattice(out["rows"], out["cols"])
            assert out["n"] in (out["rows"] * out["cols"],
                                out["rows"] * (out["cols"] - 1) + out["cols"] * (out["rows"] - 1))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * len(payload) + 100_000  # nothing sized by a declared count the bytes do not back


def test_a_declared_lattice_beyond_the_limit_is_refused_before_its_size_is_compared():
    big = HEADER.pack(b"CSNP", 1, 0, 5000, 5000, 49_990_000, 0, 0, 0.0, 0.0)
    with pytest.raises(ValueError, match="more than a sheet's 32,767"):
        decode_snapshot(big)


def test_a_snapshot_whose_count_is_not_its_lattices_links_is_refused():
    n = 12  # a 3x3 lattice has 12 links: declare 13 and send 13's bytes
    bad = HEADER.pack(b"CSNP", 1, 0, 3, 3, n + 1, 0, 0, 0.0, 0.0) + bytes(14 * (n + 1))
    with pytest.raises(ValueError, match="13 links for a 3x3 lattice of 12"):
        decode_snapshot(bad)


@FUZZ
@given(st.binary(max_size=200) | st.sampled_from([b"[" * 100_000, b'{"a":' * 50_000, b"[]", b"1", b"null"]))
def test_info_answers_that_are_not_a_json_object_are_refused(raw):
    try:
        doc = decode_info(raw)
    except ValueError:
        return
    assert isinstance(doc, dict)


@pytest.mark.parametrize("doc, says", [
    ({"rows": 1, "cols": 1, "link_length_m": 0.01}, "1x1 lattice"),
    ({"rows": 5000, "cols": 5000, "link_length_m": 0.01}, "more than a sheet's"),
    ({"rows": 3, "cols": 3, "link_length_m": float("nan")}, "link_length_m nan"),
    ({"rows": 3, "cols": 3, "link_length_m": 1e308}, r"link_length_m 1e\+308"),
    ({"rows": "3", "cols": [3], "link_length_m": 0.01}, "lacks rows"),
    ({"rows": 1e400, "cols": 3, "link_length_m": 0.01}, "lacks rows"),
])
def test_an_info_that_is_not_a_sheet_is_refused_naming_the_field(doc, says):
    with pytest.raises(ValueError, match=says):
        SheetWork("s").set_info(doc)


def _snapshot_of(rows, cols, readings, valid, counter):
    from types import SimpleNamespace
    n = readings.shape[0]
    return encode_snapshot(SimpleNamespace(readings=readings, valid=valid, status=np.zeros(n, np.uint8),
                                           counter=counter, timestamp=float(counter), wall_time=float(counter)),
                           rows, cols)


@FUZZ
@given(st.data())
def test_a_worker_sheet_takes_any_bytes_and_any_readings_without_raising(data):
    """Well-formed snapshots of arbitrary (NaN, inf, huge) readings and masks, mixed with junk:
    each is estimated, flagged not estimated, or counted bad; nothing raises."""
    w = SheetWork("s", method="global")
    w.set_info({"rows": 3, "cols": 3, "link_length_m": 0.01})
    floats = st.floats(width=32, allow_nan=True, allow_infinity=True)
    made = 0
    for counter in range(data.draw(st.integers(1, 4))):
        if data.draw(st.booleans()):
            readings = np.array(data.draw(st.lists(floats, min_size=36, max_size=36)), dtype=float).reshape(12, 3)
            valid = np.array(data.draw(st.lists(st.booleans(), min_size=12, max_size=12)))
            payload = _snapshot_of(3, 3, readings, valid, counter)
        else:
            payload = data.draw(payloads)
        out = w.work(payload, float(counter))
        made += out is not None
        if out is not None:
            assert decode_estimate(out)["rows"] == 3
    assert w.estimated + sum(w.not_estimated.values()) == made
    assert made + w.seq.duplicates + w.seq.old == w.seq.received


def test_header_layout_is_what_the_page_says():
    assert HEADER.size == 40 and struct.calcsize("<4sBBHHIHQdd") == 40
