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
