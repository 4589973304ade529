"""A virtual sheet starts without scipy: the default (curved) sheet's boundary lines and the chips'
and gyroscopes' misalignments are computed with numpy (`virtual_sheet.geometry.bracketed_root`,
`protocol.rotations.rotvec_matrices`), where importing scipy.optimize and scipy.spatial for one
root finder and one Rodrigues formula cost ~1.5 s of CPU at the start of every ``capsheet virtual``
(the test suite starts a few hundred). Both give what scipy's ``brentq`` and
``Rotation.from_rotvec`` gave, to the last bits (the rotations: tests/protocol/test_rotations.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from virtual_sheet.geometry import bracketed_root

PROBE = """
import json, sys
from virtual_sheet.sheet import VirtualSheet
from virtual_sheet.sensor import chip_error_model
VirtualSheet("gaussian", "5x4", seed=3)
VirtualSheet("gaussian", "3x3", seed=3, sensor=chip_error_model("realistic", noise_pct_g=0.1, chip_seed=7))
VirtualSheet("gaussian", "3x3", seed=3, sensors="accel+gyro+mag")
VirtualSheet("board", "3x3", seed=7, sensors="accel+gyro+mag")
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] == "scipy")[:5]))
"""


def test_the_default_curved_sheet_with_chip_errors_and_imus_is_made_without_scipy():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def _rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


@pytest.mark.parametrize("seed", range(6))
def test_bracketed_root_finds_brentqs_root_inside_the_bracket(seed):
    """Increasing functions of the kind the boundary lines solve (a distance along a bumpy surface
    minus the link length), steep and flat: the same root as scipy's ``brentq`` at the tolerance
    the net used, every evaluation inside the bracket, in a few dozen evaluations at most."""
    from scipy.optimize import brentq
    g = _rng(seed)
    for _ in range(200):
        L = 10.0 ** g.uniform(-3, 0)
        amp, freq = g.uniform(0.0, 0.9), g.uniform(0.1, 1.5)  # |dz/dt| < 1: distance increases with t
        seen = []

        def f(t, L=L, amp=amp, freq=freq):
            seen.append(t)
            z = amp * L / freq * np.sin(freq * t / L)
            return np.sqrt(t * t + z * z) - L
        f_hi = f(L)
        want = brentq(f, 0.0, L, xtol=1e-16 * L, rtol=1e-15, maxiter=200)
        seen.clear()
        got = bracketed_root(f, 0.0, L, -L, f_hi, tol=1e-16 * L)
        assert abs(got - want) <= 4e-15 * L, (got, want, L)
        assert all(0.0 < t < L for t in seen) and len(seen) <= 60, len(seen)
