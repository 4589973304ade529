"""`capsheet paper ...`: the paper's experiments end to end (quick mode: a reduced-trial run of the
same path as the full one), their setup, and bad values."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from host.cli import main, paper


@pytest.mark.parametrize("figure", ["solvability", "gaussian", "noise"])
def test_paper_subcommand_writes_png_and_tables(figure, tmp_path, capsys):
    assert main(["paper", figure, "--quick", "--out", str(tmp_path)]) == 0
    for ext in ("png", "md", "json"):
        assert (tmp_path / f"{figure}.{ext}").stat().st_size > 0
    data = json.loads((tmp_path / f"{figure}.json").read_text())
    out = capsys.readouterr().out
    assert "|" in out  # the table is printed
    if figure == "noise":
        # Fig. 9's target, the tilted one and the compass-built net
        assert set(data["targets"]) == {"fig9", "fig9-tilted", "fig9-compass"}
        assert data["trials"] == 2 and data["paper_options"]["select"] == "first"
        for t in data["targets"].values():
            rows = t["rows"]
            assert [r["noise_pct_g"] for r in rows] == [0.0, 1.0, 5.0]
            assert all(r["samples"] == 196 * 2 for r in rows)
            zero = rows[0]
            assert zero["global"]["mean_pct"] < 1e-3 < zero["paper"]["mean_pct"]  # eq. (6)'s floor
            assert t["solvability"]["units"] == 169 and len(t["solvability"]["map"]) == 13


def test_the_experiment_reproduces_the_papers_claim_and_its_failure_with_min_selection(tmp_path, capsys):
    # the paper (section 3.3): under the 5 % line up to 5 % g. Its method as read by default
    # meets that on the Fig. 9 target; taking the smallest eq. (8) of all starts does not
    # (docs/estimator.md section 7). Two trials: the whole experiment is `capsheet paper noise`.
    target = paper.build_target("fig9")
    methods = {"paper": {"method": "paper"},
               "min": {"method": "paper",
                       "paper_options": paper.paper_options(["select=min"])}}
    rows = paper.noise_study(target, (5.0,), 2, 2008, methods=methods)
    assert rows[0]["paper"]["mean_pct"] < paper.FAILURE_LINE_PCT < rows[0]["min"]["mean_pct"]
    assert paper.works_up_to(rows, "paper") == 5.0 and paper.works_up_to(rows, "min") is None


def test_the_fig9_target_is_the_paper_setup():
    from virtual_sheet.geometry import ideal_readings, link_lengths

    t = paper.build_target("fig9")
    P = t.joints
    assert P.shape == (14, 14, 3)  # 13x13 units
    np.testing.assert_allclose(link_lengths(P), paper.LINK_LENGTH, rtol=1e-9)  # stiff links
    # on the Gaussian A = σ = S/4 (laid over it, every joint on the surface)
    a = s = 13 * paper.LINK_LENGTH / 4
    z = a * np.exp(-(P[..., 0] ** 2 + P[..., 1] ** 2) / (2 * s * s))
    np.testing.assert_allclose(P[..., 2], z, atol=1e-9)
    np.testing.assert_allclose(t.readings, ideal_readings(P))
    # laid flat and relaxed, not the compass net: the two differ by millimetres at the corners
    c = paper.build_target("fig9-compass").joints
    assert 1e-3 < np.abs(P - c).max() < 1e-2
    # the second target: the same sheet, tilted beyond the bump's steepest slope: no level unit
    sv = paper.unit_solvability(paper.build_target("fig9-tilted"))
    assert (sv < 0.1).sum() == 0 and (paper.unit_solvability(t) < 0.1).sum() >= 1


def test_noise_draws_are_the_same_for_every_method_and_run_of_a_level():
    r0 = np.zeros((5, 3))
    a = paper.noise_draws(r0, 5.0, 3, 7)
    b = paper.noise_draws(r0, 5.0, 3, 7)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], paper.noise_draws(r0, 4.0, 1, 7)[0])  # per level
    big = paper.noise_draws(np.zeros((20000, 3)), 5.0, 1, 1)[0]
    assert abs(big.std() / (0.05 * 9.80665) - 1) < 0.01  # normal: the level is the std
    u = paper.noise_draws(np.zeros((20000, 3)), 5.0, 1, 1, "uniform")[0]
    assert np.abs(u).max() <= 0.05 * 9.80665 and abs(u.std() * np.sqrt(3) / (0.05 * 9.80665) - 1) < 0.01


def test_solvability_legend_and_table_count_the_same_states(tmp_path, capsys):
    import matplotlib.pyplot as plt

    from host.cli.figures import solvability_figure

    res = paper.solvability_grid(8)
    for crit in ("eq7", "yaw_std"):
        c = res[crit]
        assert sum(c[k] for k, _ in paper.CASE_GROUPS) == c["flagged"]  # a partition
    assert res["eq7"]["flagged"] == int((res["ratio"] < 0.1).sum())
    fig = solvability_figure(tmp_path / "s.png", res, paper.CASE_GROUPS, paper._cases)
    try:
        for ax, crit in zip(fig.axes, ("eq7", "yaw_std")):
            texts = [t.get_text() for t in ax.get_legend().get_texts()]
            counts = [int(t.split("(")[1].split(")")[0].replace(",", "")) for t in texts]
            assert sum(counts) == res[crit]["flagged"]  # the legend adds up to the flagged states
            assert texts[0].startswith("Case 2") and "not drawn" in texts[0]
        assert "projected out" in fig.texts[-1].get_text()
    finally:
        plt.close(fig)
    assert main(["paper", "solvability", "--quick", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "solvability.md").read_text()
    assert f"**{res['eq7']['flagged']:,}**" in md and f"**{res['yaw_std']['flagged']:,}**" in md


@pytest.mark.parametrize("argv, message", [
    (["noise", "--trials", "0"], "--trials: invalid value '0' (need an integer >= 1)"),
    (["noise", "--trials", "x"], "--trials: invalid value 'x'"),
    (["noise", "--target", "cube"], "--target: unknown target 'cube'"),
    (["noise", "--seed", "-1"], "--seed: invalid value '-1'"),
    (["noise", "--paper-option", "combine"], "expected KEY=VALUE"),
    (["noise", "--paper-option", "n_starts=two"], "n_starts is an integer"),
    (["gaussian", "--noise", "-1"], "--noise: invalid noise '-1'"),
    (["gaussian", "--noise", "nan"], "--noise: invalid noise 'nan'"),
    (["solvability", "--steps", "1"], "--steps: invalid value '1' (need an integer >= 2)"),
])
def test_bad_values_are_one_line_and_exit_2(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["paper", *argv, "--out", str(tmp_path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and err.startswith("capsheet paper ")
    assert not list(tmp_path.iterdir())  # nothing was run


def test_a_bad_paper_option_value_is_one_line_through_the_real_cli(tmp_path):
    p = subprocess.run([sys.executable, "-m", "host.cli", "paper", "noise", "--paper-option",
                        "combine=stitch", "--out", str(tmp_path)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.count("\n") == 1 and "combine" in p.stderr


def test_paper_without_figure_prints_help(capsys):
    assert main(["paper"]) == 2
    assert "solvability" in capsys.readouterr().out
