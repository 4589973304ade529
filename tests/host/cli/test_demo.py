"""`capsheet demo` end to end: virtual sheet on a real pty in its own process, host via pyserial,
live estimation against the virtual truth. Short run; the same code path as `make demo`."""

import json
import subprocess
import sys


def test_demo_streams_estimates_and_meets_its_error_target(tmp_path):
    png = tmp_path / "demo.png"
    out = subprocess.run([sys.executable, "-m", "host.cli", "demo", "--duration", "2.5", "--out", str(png), "--json"],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    result = json.loads(out.stdout[out.stdout.index("{"):])
    assert result["pass"] is True
    assert result["snapshots"] >= 0.5 * result["rate_hz"] * 2.5
    assert result["compared_with_truth"] >= 5
    assert result["mean_error_pct_side"] <= 1.0
    assert "364 chips discovered, 364 assigned" in out.stderr
    assert png.stat().st_size > 10_000


def test_a_shape_the_demo_cannot_build_is_one_line_and_exit_2():
    """`demo --shape heightmap` needs a .npy path the demo has no option for (was a traceback)."""
    out = subprocess.run([sys.executable, "-m", "host.cli", "demo", "--shape", "heightmap", "--duration", "1"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "heightmap needs" in out.stderr and "Traceback" not in out.stderr
