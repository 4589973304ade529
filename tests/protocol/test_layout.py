"""protocol/layout.py: the one layout file format, read by the host and written by the virtual
sheet — one uid rule (hex, 0x optional), every malformed file a one-line `LayoutError`."""

from __future__ import annotations

import pytest

from protocol.layout import LayoutError, format_layout, load_layout, parse_layout, parse_uid, save_layout

UIDS = {0x0123456789ABCDEF: 0, 0xA: 1, 0xFFFFFFFFFFFFFFFF: 2}


@pytest.mark.parametrize("name", ["s.csv", "s.json", "s.txt"])
def test_round_trip_both_formats(tmp_path, name):
    path = save_layout(tmp_path / name, UIDS, rows=2, cols=2)
    doc = load_layout(path)
    assert doc.links == UIDS
    assert doc.lattice == ("2x2" if name.endswith(".json") else None)  # CSV carries no lattice


@pytest.mark.parametrize("text,uid", [("0x0A", 10), ("0XA", 10), ("a", 10), ("10", 16), (" ff ", 255),
                                      ("0xFFFFFFFFFFFFFFFF", (1 << 64) - 1), ("1e3", 0x1E3), ("0b101", 0xB101)])
def test_one_uid_rule_hex_with_optional_prefix(text, uid):
    assert parse_uid(text) == uid


@pytest.mark.parametrize("text", ["", "0x", "0x1FFFFFFFFFFFFFFFF", "12g", "-1", "0o17", "1.5", "0x 1"])
def test_bad_uids_are_refused(text):
    with pytest.raises(LayoutError, match="invalid uid"):
        parse_uid(text)


def test_the_virtual_sheet_and_the_host_read_the_same_file(tmp_path):
    from host.session.core import Layout
    from protocol.layout import load_layout
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("flat", "3x3", seed=4)
    for name in ("v.csv", "v.json"):
        path = sheet.write_layout(tmp_path / name)
        assert dict(load_layout(path).links) == Layout.load(path).links == dict(sheet.layout)
    assert Layout.load(tmp_path / "v.json").lattice == "3x3"
    # a hand-written file without 0x: both read it as hex
    (tmp_path / "hand.csv").write_text("uid,link\n10,0\n")
    assert dict(load_layout(tmp_path / "hand.csv").links) == Layout.load(tmp_path / "hand.csv").links == {16: 0}


BAD = {
    "truncated.json": ('{"rows": 2, "cols": 2, "chips": [{"uid": "0x1", "li', "not valid JSON"),
    "list.json": ("[1, 2]", "expected a JSON object"),
    "types.json": ('{"chips": [{"uid": 5, "link": 0}]}', "uid must be a hex string"),
    "link.json": ('{"chips": [{"uid": "0x5", "link": "zero"}]}', "invalid link 'zero'"),
    "neg.json": ('{"chips": [{"uid": "0x5", "link": -1}]}', "need >= 0"),
    "rows.json": ('{"rows": "2", "cols": 2, "chips": []}', "invalid rows '2'"),
    "nochips.json": ('{"rows": 2, "cols": 2}', "'chips' must be a list"),
    "format.json": ('{"format": "other", "chips": []}', "is not 'capsheet-layout'"),
    "dup.csv": ("uid,link\n0x1,0\n0x1,1\n", "appears twice"),
    "twolinks.csv": ("uid,link\n0x1,0\n0x2,0\n", "Link 0 is given to two chips"),
    "cols.csv": ("uid,link\n0x1,0,7\n", "expected 'uid,link'"),
    "decimal-link.csv": ("uid,link\n0x1,0x2\n", "invalid link '0x2'"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_malformed_files_are_one_line_errors_naming_the_place(tmp_path, name):
    text, needle = BAD[name]
    (tmp_path / name).write_text(text)
    with pytest.raises(LayoutError) as info:
        load_layout(tmp_path / name)
    msg = str(info.value)
    assert needle in msg and name in msg and "\n" not in msg


def test_binary_and_missing_files(tmp_path):
    (tmp_path / "bin.csv").write_bytes(bytes(range(256)))
    with pytest.raises(LayoutError, match="binary data"):
        load_layout(tmp_path / "bin.csv")
    (tmp_path / "nul.csv").write_bytes(b"uid,link\n\x00\x01,0\n")
    with pytest.raises(LayoutError, match="binary data"):
        load_layout(tmp_path / "nul.csv")
    with pytest.raises(LayoutError, match="cannot read layout file"):
        load_layout(tmp_path / "absent.csv")


def test_format_is_stable_and_sorted_by_link():
    assert format_layout({0xB: 1, 0xA: 0}) == "uid,link\n0x000000000000000A,0\n0x000000000000000B,1\n"
    assert parse_layout(format_layout({0xB: 1}, "x.json", 2, 3), "x.json").lattice == "2x3"
