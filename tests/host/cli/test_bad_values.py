"""Every subcommand's command line: a bad value is ONE short line on stderr that names the option,
exit status 2, no traceback, no hang, nothing written, nothing started.

Each case runs through the command's entry point in this process (tests/host/cli/conftest.py's
`cli_here`: the same parser and checks, a deadline for a hang); the first case of each subcommand
(`REAL`) runs through a real process as well (``python -m host.cli``, a timeout), where the line is
what the interpreter itself printed.

The table is what a careless hand types: sizes no memory or bus holds, zero and negative lengths,
durations and rates, paths whose folder is missing or that name a folder, files that exist and would
be lost, an output that is the command's own input."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

CLI = [sys.executable, "-m", "host.cli"]
#: a bad value must be refused well within this (a hang or a 3 GB allocation took 25 s and more)
TIMEOUT_S = 60
#: "one short line": what a terminal shows without wrapping much
MAX_LINE = 240


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """``{name: path}`` of files a case refers to (by ``{name}`` in its arguments)."""
    d = tmp_path_factory.mktemp("bad-values")
    made = {"dir": d / "a-folder", "mcap": d / "precious.mcap", "csv": d / "precious.csv",
            "json": d / "precious.json", "npz": d / "precious.npz", "txt": d / "notes.txt",
            "log": d / "precious.log"}
    made["dir"].mkdir()
    for k, p in made.items():
        if k != "dir":
            p.write_bytes(b"mine, not yours\n")
    made["under_file"] = made["txt"] / "x"  # a path whose "folder" is a regular file
    made["nodir"] = d / "no-such-folder" / "x"
    return {k: str(v) for k, v in made.items()}


#: (subcommand and arguments, the option the line must name). ``{name}`` is a `files` path.
CASES = [
    # -- demo: sizes, lengths, rates, durations, outputs, capacity (post-parse, still exit 2) --
    (["demo", "--lattice", "1000000x2"], "--lattice"),
    (["demo", "--lattice", "200x200"], "--lattice"),
    (["demo", "--lattice", "1x5"], "--lattice"),
    (["demo", "--link-length", "0"], "--link-length"),
    (["demo", "--link-length", "-1"], "--link-length"),
    (["demo", "--link-length", "nan"], "--link-length"),
    (["demo", "--rate", "0"], "--rate"),
    (["demo", "--rate", "inf"], "--rate"),
    (["demo", "--duration", "-1"], "--duration"),
    (["demo", "--noise", "-1"], "--noise"),
    (["demo", "--min-complete", "101"], "--min-complete"),
    (["demo", "--seed", "-1"], "--seed"),
    (["demo", "--gateways", "0"], "--gateways"),
    (["demo", "--out", "{under_file}.png"], "--out"),
    (["demo", "--out", "demo.txt"], "--out"),
    (["demo", "--record", "{mcap}"], "--record"),
    (["demo", "--record", "{nodir}.mcap"], "--record"),
    (["demo", "--live", "70000"], "--live"),
    (["demo", "--calibration", "{nodir}.json"], "--calibration"),
    (["demo", "--lattice", "32x32", "--packed", "--rate", "1000"], "--rate"),
    # -- virtual --
    (["virtual", "--lattice", "1000000x2"], "--lattice"),
    (["virtual", "--link-length", "0"], "--link-length"),
    (["virtual", "--duration", "-1"], "--duration"),
    (["virtual", "--rate", "0"], "--rate"),
    (["virtual", "--noise", "-1"], "--noise"),
    (["virtual", "--bus-count", "0"], "--bus-count"),
    (["virtual", "--gateways", "0"], "--gateways"),
    (["virtual", "--seed", "-1"], "--seed"),
    (["virtual", "--layout-out", "{nodir}.csv"], "--layout-out"),
    (["virtual", "--layout-out", "layout.txt"], "--layout-out"),
    (["virtual", "--transport", "memory", "--layout-out", "{csv}"], "--layout-out"),
    (["virtual", "--symlink", "{dir}"], "--symlink"),
    (["virtual", "--symlink", "{txt}"], "--symlink"),
    (["virtual", "--symlink", "{nodir}"], "--symlink"),
    # -- host --
    (["host", "--port", "/dev/null", "--lattice", "200x200"], "--lattice"),
    (["host", "--port", "/dev/null", "--rate", "0"], "--rate"),
    (["host", "--port", "/dev/null", "--duration", "-1"], "--duration"),
    (["host", "--port", "/dev/null", "--link-length", "0"], "--link-length"),
    (["host", "--port", "/dev/null", "--record", "{mcap}"], "--record"),
    (["host", "--can", "virtual:x", "--can-log", "{log}"], "--can-log"),
    (["host", "--port", "/dev/null", "--layout", "{nodir}.csv"], "--layout"),
    (["host", "--port", "/dev/null", "--baud", "0"], "--baud"),
    (["host", "--port", "/dev/null", "--ack-timeout-ms", "0"], "--ack-timeout-ms"),
    (["host", "--port", "/dev/null", "--watchdog-ms", "-5"], "--watchdog-ms"),
    (["host", "--port", "/dev/null", "--watchdog-ms", "nan"], "--watchdog-ms"),
    # -- calibrate: the output is checked before any pose is asked for --
    (["calibrate", "--port", "/dev/null", "--out", "{nodir}.json"], "--out"),
    (["calibrate", "--port", "/dev/null", "--out", "{json}"], "--out"),
    (["calibrate", "--port", "/dev/null", "--out", "cal.txt"], "--out"),
    (["calibrate", "--port", "/dev/null", "--out", "{dir}"], "--out"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--lattice", "200x200"], "--lattice"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--samples", "0"], "--samples"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--rate", "-3"], "--rate"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--timeout", "0"], "--timeout"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--gravity", "0"], "--gravity"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--ack-timeout-ms", "-1"], "--ack-timeout-ms"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--watchdog-ms", "0"], "--watchdog-ms"),
    (["calibrate", "--port", "/dev/null", "--out", "c.json", "--max-turn-residual-deg", "-1"], "--max-turn-residual-deg"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "3x3", "--ack-timeout-ms", "inf"], "--ack-timeout-ms"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "3x3", "--watchdog-ms", "0"], "--watchdog-ms"),
    # -- tactile --
    (["tactile", "--duration", "-1"], "--duration"),
    (["tactile", "--lattice", "1000000x2"], "--lattice"),
    (["tactile", "--link-length", "0"], "--link-length"),
    (["tactile", "--thickness", "0"], "--thickness"),
    (["tactile", "--poisson", "0.7"], "--poisson"),
    (["tactile", "--snapshot-rate", "0"], "--snapshot-rate"),
    (["tactile", "--out", "heat.txt"], "--out"),
    (["tactile", "--record", "{mcap}"], "--record"),
    (["tactile", "--indenter", "thumb"], "--indenter"),
    (["tactile", "--indenter", ""], "--indenter"),
    (["tactile", "--port", "/dev/null", "--ack-timeout-ms", "0"], "--ack-timeout-ms"),
    (["tactile", "--port", "/dev/null", "--watchdog-ms", "1e9"], "--watchdog-ms"),
    # -- replay and estimate: inputs exist, outputs are not inputs --
    (["replay", "{nodir}.mcap"], "recording"),
    (["replay", "{dir}"], "recording"),
    (["replay", "{mcap}", "--speed", "0"], "--speed"),
    (["replay", "{mcap}", "--record", "{mcap}", "--overwrite"], "--record"),
    (["estimate", "{nodir}.mcap", "--out", "j.npz"], "recording"),
    (["estimate", "{mcap}", "--out", "{mcap}", "--overwrite"], "--out"),
    (["estimate", "{mcap}", "--out", "{npz}"], "--out"),
    (["estimate", "{mcap}", "--out", "j.txt"], "--out"),
    (["estimate", "{mcap}", "--out", "j.npz", "--jobs", "0"], "--jobs"),
    (["estimate", "{mcap}", "--out", "j.npz", "--png", "j.txt"], "--png"),
    (["estimate", "{mcap}", "--out", "j.npz", "--method", "kalman"], "--method"),
    # -- conformance and protocol --
    (["conformance", "--port", "/dev/null", "--timeout", "0"], "--timeout"),
    (["conformance", "--port", "/dev/null", "--node", "0x8000"], "--node"),
    (["conformance", "--port", "/dev/null", "--slack-ms", "-1"], "--slack-ms"),
    (["protocol", "encode", "SAMPLE", "node=1"], "counter"),
    (["protocol", "encode", "SAMPLE", "node=1", "counter=abc", "x=0", "y=0", "z=0"], "counter"),
    (["protocol", "encode", "SAMPLE", "node=1", "bogus=3"], "bogus"),
    (["protocol", "capacity", "--rate", "0"], "--rate"),
    (["protocol", "capacity", "--lattice", "1x1"], "--lattice"),
    # an unknown scene names every kind there is, the moving ones too
    (["demo", "--shape", "nope"], "carry"),
    (["virtual", "--shape", "nope"], "carry"),
    # -- paper: argparse's own errors are one line too --
    (["paper", "gaussian", "--seed", "abc"], "--seed"),
    # an abbreviation is not taken for a longer option (--noise is not --noise-dist)
    (["paper", "noise", "--noise", "5"], "unrecognized arguments: --noise"),
    (["host", "--port", "/dev/null", "--dur", "3"], "unrecognized arguments: --dur"),
    # what a subcommand does not know is reported under its own name, not the top level's
    (["host", "--port", "/dev/null", "--bogus"], "capsheet host: unrecognized arguments: --bogus"),
    (["paper", "gaussian", "--bogus", "1"], "capsheet paper gaussian: unrecognized arguments: --bogus 1"),
    (["protocol", "capacity", "--zz"], "capsheet protocol capacity: unrecognized arguments: --zz"),
    (["--bogus"], "capsheet: unrecognized arguments: --bogus"),
]


def _ids():
    return [" ".join(a) for a, _ in CASES]


#: the cases that also run through a real process: the first of each subcommand (and the top level)
REAL = {next(k for k, (a, _) in enumerate(CASES) if a[0] == cmd) for cmd in {a[0] for a, _ in CASES}}


@pytest.mark.parametrize("argv, option", CASES, ids=_ids())
def test_a_bad_value_is_one_line_and_exit_2(argv, option, files, tmp_path, cli_here, request):
    argv = [a.format(**files) for a in argv]
    before = {k: open(p, "rb").read() for k, p in files.items() if os.path.isfile(p)}
    runs = [cli_here(argv, cwd=tmp_path, timeout_s=TIMEOUT_S)]
    if CASES.index((request.node.callspec.params["argv"], option)) in REAL:
        out = subprocess.run(CLI + argv, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path,
                             stdin=subprocess.DEVNULL)
        runs.append((out.returncode, out.stdout, out.stderr))
    for code, _stdout, stderr in runs:
        _one_line(code, stderr, option)
        # nothing the user had was touched, nothing was written where the command runs
        assert {k: open(p, "rb").read() for k, p in files.items() if os.path.isfile(p)} == before
        assert os.listdir(tmp_path) == []


def _one_line(code: int, stderr: str, option: str) -> None:
    err = stderr.strip()
    assert "Traceback" not in stderr, stderr
    assert code == 2, f"exit {code}; stderr:\n{stderr}"
    lines = err.splitlines()
    assert len(lines) == 1, f"{len(lines)} lines on stderr:\n{stderr}"
    assert len(lines[0]) <= MAX_LINE, lines[0]
    assert option in lines[0], f"the line does not name {option}: {lines[0]}"
    assert lines[0].startswith("capsheet"), lines[0]


#: a port that does not exist is not a usage error (the value is well formed): one line, exit 1
@pytest.mark.parametrize("argv", [
    ["tactile", "--port", "/dev/ttyNOPE"],
    ["host", "--port", "/dev/ttyNOPE"],
    ["calibrate", "--port", "/dev/ttyNOPE", "--out", "cal.json"],
], ids=lambda a: " ".join(a))
def test_a_missing_port_is_one_line(argv, tmp_path):
    out = subprocess.run(CLI + argv, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path,
                         stdin=subprocess.DEVNULL)
    assert "Traceback" not in out.stderr, out.stderr
    assert out.returncode == 1, out.stderr
    lines = [ln for ln in out.stderr.strip().splitlines() if "auto-assigning" not in ln]
    assert len(lines) == 1 and "/dev/ttyNOPE" in lines[0], out.stderr
    assert os.listdir(tmp_path) == []
