"""Untrusted files (recordings, layouts, calibrations, robot configs, CAN logs): every crafted file of
tests/host/record/crafted.py is refused by every command that reads such a file — one line on stderr,
no traceback, exit 2 for a config file (exit 1 or 2 for a recording or a CAN log), within 60 s and
under 600 MB of peak RSS (the kernel's figure for the process that read it). The control, a real
session's recording, is read fine by the same commands (the refusals are not blanket ones)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.host.record.crafted import argv, corpus
from tests.shared_runs import session_root, shared_once

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
MAX_RSS_MB = 600
MAX_SECONDS = 60


def _drive(commands: list, folder: Path) -> dict:
    spec = folder / "commands.json"
    spec.write_text(json.dumps(commands))
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("ZENOH")}, "OPENBLAS_NUM_THREADS": "1",
           "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(HERE / "refuse_driver.py"), str(spec)], capture_output=True, text=True,
                         timeout=60 * len(commands), cwd=ROOT, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    return {(r["name"], r["argv"][0]): r for r in rows}


@pytest.fixture(scope="module")
def results(tmp_path_factory, request):
    """``({file: kind}, {(file, command): row})``: every command on every crafted file, made once per
    test session (tests/shared_runs.py): each worker that reached this module ran all of them before
    (~20 s of CPU, 80 s on a busy machine), and made its own real recording for the control."""
    def make():
        folder = tmp_path_factory.mktemp("crafted")
        files = corpus(folder / "in")
        (folder / "out").mkdir()
        commands = []
        for name, (path, kind) in files.items():
            for a in argv(path, kind, folder / "out"):
                commands.append([name, a])
        # the control: a real session's recording (tests/host/conftest.py), raw input and all
        recording = request.getfixturevalue("pty_recording")
        commands += [["good_control", a] for a in argv(recording, "recording", folder / "out")]
        return {"files": {name: kind for name, (_path, kind) in files.items()},
                "rows": list(_drive(commands, folder).values())}
    doc = shared_once(session_root(tmp_path_factory), "untrusted-files", make)
    files = {name: (None, kind) for name, kind in doc["files"].items()}
    return files, {(r["name"], r["argv"][0]): r for r in doc["rows"]}


def test_every_crafted_file_is_refused_in_one_line_within_60_s_and_600_mb(results):
    files, got = results
    bad = []
    for (name, cmd), r in sorted(got.items()):
        if name == "good_control":
            continue
        kind = files[name][1]
        lines = [ln for ln in r["stderr"].splitlines() if ln.strip()]
        codes = {2} if kind in ("layout", "calibration", "robot") else {1, 2}
        problems = []
        if r["exit"] not in codes:
            problems.append(f"exit {r['exit']}")
        if len(lines) != 1 or "Traceback" in r["stderr"]:
            problems.append(f"{len(lines)} lines")
        if r["seconds"] > MAX_SECONDS:
            problems.append(f"{r['seconds']} s")
        if r["maxrss_mb"] > MAX_RSS_MB:
            problems.append(f"{r['maxrss_mb']} MB")
        if problems:
            bad.append(f"{name} ({cmd}): {', '.join(problems)}: {r['stderr'][-400:]!r}")
    assert bad == [], "\n".join(bad)
    assert {n for n, _ in got} >= set(files)  # every file was run


@pytest.mark.parametrize("name, says", [
    ("chunk_declares_2gib", "declaring 2,147,483,648 bytes decompressed"),
    ("forty_chunks_of_48_mib", "more than 100 times the file's"),
    ("chunk_holds_more", "decompresses to more than the 1,024 bytes it declares"),
    ("lattice_1e8_links", "10000x5000 lattice of 99,985,000 links"),
    ("n_links_1e8", "n_links 100,000,000"),
    ("link_length_nan", "link_length_m nan"),
    ("snapshot_declares_32767_links", "a snapshot message of 32767 links with 0 valid values"),
    ("dev_zero", "a device, not a regular file"),
    ("fifo", "a FIFO, not a regular file"),
    ("no_valid_link", "none of the 12 snapshots|made no snapshot"),
    ("layout_5000x5000", "more than a sheet's 32,767"),
    ("cal_misalignment_1e308", "chip 0: misalignment 1e+308"),
    ("cal_bias_nan", "chip 0: bias nan"),
    ("cal_sparse_1gb", "1,073,741,824 bytes"),
    ("robot_nested", "nested too deep"),
    ("robot_translation_1e300", "more than 1000 m"),
    ("canlog_dev_zero", "a device, not a regular file"),
    ("canlog_blf_zlib_bomb", "a log container inflating to more than 16,777,216 bytes"),
])
def test_the_line_names_what_is_wrong(results, name, says):
    _, got = results
    lines = [r["stderr"] for (n, _), r in got.items() if n == name]
    assert lines and all(any(w in s for w in says.split("|")) for s in lines), lines


def test_the_real_recording_they_are_made_from_is_read(results):
    _, got = results
    for cmd in ("estimate", "replay"):
        r = got[("good_control", cmd)]
        assert r["exit"] == 0, r["stderr"]


def test_figures(results, capsys):
    """The peak RSS and time of each refusal, printed (pytest -s) for the record."""
    _, got = results
    worst = max(got.values(), key=lambda r: r["maxrss_mb"])
    slowest = max(got.values(), key=lambda r: r["seconds"])
    print(json.dumps({"commands": len(got), "max_rss_mb": worst["maxrss_mb"], "max_rss_of": worst["name"],
                      "max_seconds": slowest["seconds"], "max_seconds_of": slowest["name"]}))
    assert worst["maxrss_mb"] < MAX_RSS_MB
