"""protocol/files.py: untrusted files are opened only if regular, read only up to a cap, parsed with
bounded nesting; each refusal one line naming the file."""

from __future__ import annotations

import os
import threading

import pytest

from protocol.files import MAX_LINKS, depth, loads_json, loads_toml, open_regular, read_file


def test_the_link_limit_is_the_node_id_space_and_the_cli_s():
    from host.cli.argtypes import MAX_LINKS as CLI_MAX
    from protocol.messages import NODE_MAX_ASSIGNED
    assert MAX_LINKS == NODE_MAX_ASSIGNED == CLI_MAX == 0x7FFF


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    fifo = tmp_path / "f.json"
    os.mkfifo(fifo)
    done = []
    th = threading.Thread(target=lambda: done.append(pytest.raises(ValueError, open_regular, fifo)), daemon=True)
    th.start()
    th.join(5.0)
    assert done and "a FIFO, not a regular file" in str(done[0].value)


@pytest.mark.parametrize("path, says", [("/dev/zero", "a device"), ("/", "a folder")])
def test_devices_and_folders_are_refused_before_reading(path, says):
    with pytest.raises(ValueError, match=says):
        read_file(path, 10, "a file")


def test_a_file_over_the_cap_is_refused_by_its_size_unread(tmp_path):
    p = tmp_path / "sparse"
    with open(p, "wb") as f:
        f.truncate(1 << 40)  # a terabyte, sparse: only its size is looked at
    with pytest.raises(ValueError, match="1,099,511,627,776 bytes, more than"):
        read_file(p, 1 << 20, "a config")
    (tmp_path / "ok").write_bytes(b"abc")
    assert read_file(tmp_path / "ok", 3, "x") == b"abc"
    with pytest.raises(ValueError, match="more than"):
        read_file(tmp_path / "ok", 2, "x")


def test_a_missing_file_is_the_os_error_open_gives():
    with pytest.raises(FileNotFoundError):
        read_file("/nonexistent/x", 10)


@pytest.mark.parametrize("doc, d", [(1, 0), ([], 1), ({"a": [1, {"b": []}]}, 4)])
def test_depth_counts_lists_and_dicts(doc, d):
    assert depth(doc) == d


def test_nesting_is_bounded_in_json_and_toml_and_named():
    assert loads_json("[" * 32 + "]" * 32, "x")
    with pytest.raises(ValueError, match="x: nested 33 levels deep, more than 32"):
        loads_json("[" * 33 + "]" * 33, "x")
    with pytest.raises(ValueError, match="y.json: nested too deep to read"):
        loads_json("[" * 100_000 + "]" * 100_000, "y.json")
    with pytest.raises(ValueError, match="r.toml: nested too deep to read"):
        loads_toml("a = " + "[" * 100_000 + "]" * 100_000, "r.toml")
    with pytest.raises(ValueError, match="r.toml: not TOML"):
        loads_toml("a = = 1", "r.toml")
    with pytest.raises(ValueError, match="z: not valid JSON"):
        loads_json(b"\xff\xfe{", "z")
