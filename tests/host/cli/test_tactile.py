"""``capsheet tactile`` (host/cli/tactile.py): the virtual foam sheet's estimates and contacts
recorded, and a calibration file applied. (Its bad values: tests/host/cli/test_bad_values.py.)"""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from host.analysis.calibration import Calibration
from host.record.recording import read


def capsheet(*argv, timeout=120):
    return subprocess.run([sys.executable, "-m", "host.cli", *argv], capture_output=True, text=True,
                          timeout=timeout)


def test_capsheet_tactile_records_what_it_estimates_with_the_true_contacts(tmp_path, capsys):
    """The virtual foam sheet: every snapshot the sensor estimates is recorded with its estimate and
    contacts (it recorded estimates from snapshots it never recorded: 0 snapshots, 9 estimates).
    A 6x6 sheet: what is recorded per snapshot does not depend on its size (the default 14x14 took
    twice the time to estimate the same nine snapshots)."""
    from host.cli import main
    out = tmp_path / "tactile.mcap"
    assert main(["tactile", "--lattice", "6x6", "--duration", "1", "--snapshot-rate", "8", "--record", str(out),
                 "--out", str(tmp_path / "t.png"), "-q"]) == 0
    assert "recorded 9 snapshots, 9 estimates, 9 contact frames" in capsys.readouterr().err
    rec = read(out)
    assert rec.session["mode"] == "tactile" and len(rec.contacts) == len(rec.estimates["counter"]) == len(rec) == 9
    assert rec.counter.tolist() == rec.estimates["counter"].tolist() == list(range(9))
    assert rec.valid.all() and rec.complete.all()
    assert np.allclose(rec.timestamp, rec.estimates["timestamp"])  # each snapshot with its own estimate
    detected = [c for _, _, cs in rec.contacts for c in cs if not c.get("true")]
    true = [c for _, _, cs in rec.contacts for c in cs if c.get("true")]
    assert detected and true
    assert all(c["force_n"] > 0 and len(c["position"]) == 3 for c in detected)
    assert rec.message_counts["/sheet/scene"] == 18  # lattice + contacts, per frame


def test_tactile_applies_a_calibration_file(tmp_path, cli_here):
    """The identity file gives exactly the output of no file; a file with a bias changes it. The run
    without a file through a real process (tactile's run end to end), the two with a file through
    the entry point in this process (the same command and output)."""
    ident = Calibration.identity(6, 6).save(tmp_path / "id.json")
    base = ["tactile", "--lattice", "6x6", "--duration", "1", "--snapshot-rate", "4",
            "--out", str(tmp_path / "t.png")]
    plain = capsheet(*base)
    code, with_id, err = cli_here([*base, "--calibration", str(ident)])
    assert plain.returncode == 0 and code == 0, (plain.stderr, err)
    assert plain.stdout == with_id
    c = Calibration.identity(6, 6)
    biased = Calibration(6, 6, bias=np.full((c.n_links, 3), 0.5), scale=c.scale, misalignment=c.misalignment)
    code, other, err = cli_here([*base, "--calibration", str(biased.save(tmp_path / "b.json"))])
    assert code == 0 and other != plain.stdout, err
