"""Building the ``capsheet`` parser (every command, ``--help`` included) imports no heavy library:
scipy, the estimator, the tactile pipeline, matplotlib and the file formats are imported by the
commands that use them (they cost ~0.8 s before any command could start)."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("scipy", "host.analysis.estimator", "host.analysis.tactile", "matplotlib", "mcap", "foxglove")

PROBE = """
import json, sys
from host.cli import build_parser
build_parser().format_help()
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in {"scipy", "matplotlib", "mcap", "foxglove"}
                        or m.startswith(("host.analysis.estimator", "host.analysis.tactile")))))
"""


def test_building_the_parser_imports_no_heavy_module():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert loaded == [], f"imported while building the parser: {loaded[:10]}"


def test_every_subcommand_is_still_registered():
    from host.cli import SUBCOMMAND_MODULES, build_parser
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert sorted(sub.choices) == sorted(m.rsplit(".", 1)[1] for m in SUBCOMMAND_MODULES)


RUN_PROBE = """
import contextlib, io, json, sys
from host.cli import SUBCOMMAND_MODULES, main
with contextlib.redirect_stdout(io.StringIO()):
    code = main(["protocol", "capacity", "--rate", "100", "--lattice", "4x4"])
print(json.dumps([code, sorted(m for m in SUBCOMMAND_MODULES if m in sys.modules),
                  sorted(m for m in sys.modules if m.startswith(("host.session", "host.conformance")))[:5]]))
"""


def test_a_command_builds_its_own_subcommand_alone():
    """A command's run imports its own subcommand's module, not the twelve others' (each process a
    command starts paid ~0.2 s of CPU for them): ``capsheet protocol capacity`` needs neither the
    session nor the conformance checks, which other commands' options import."""
    out = subprocess.run([sys.executable, "-c", RUN_PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    code, commands, heavy = json.loads(out.stdout.strip().splitlines()[-1])
    assert code == 0
    assert commands == ["host.cli.protocol"]
    assert heavy == []


def test_help_and_a_misspelt_command_still_list_every_command(cli_here):
    """``--help`` and a word that is no command get the whole parser: every command listed."""
    from host.cli import SUBCOMMAND_MODULES
    names = [m.rsplit(".", 1)[1] for m in SUBCOMMAND_MODULES]
    code, out, _err = cli_here(["--help"])
    assert code == 0 and all(n in out for n in names)
    code, _out, err = cli_here(["hots", "--lattice", "3x3"])
    assert code == 2 and all(repr(n) in err for n in names), err
    code, out, _err = cli_here(["--version"])
    assert code == 0 and out.startswith("capsheet ")
