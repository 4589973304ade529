"""`capsheet paper ...` runs end to end (quick mode) and writes its PNG, markdown and JSON."""

from __future__ import annotations

import json

import pytest

from host.cli import main


@pytest.mark.parametrize("figure", ["solvability", "gaussian", "noise"])
def test_paper_subcommand_writes_png_and_tables(figure, tmp_path, capsys):
    assert main(["paper", figure, "--quick", "--out", str(tmp_path)]) == 0
    for ext in ("png", "md", "json"):
        assert (tmp_path / f"{figure}.{ext}").stat().st_size > 0
    data = json.loads((tmp_path / f"{figure}.json").read_text())
    out = capsys.readouterr().out
    assert "|" in out  # the table is printed
    if figure == "noise":
        assert len(data["rows"]) == 3
        assert out.count("noise ") >= 3  # one progress line per level
        zero = data["rows"][0]
        assert zero["global"]["mean_pct"] <= zero["paper"]["mean_pct"]


def test_paper_without_figure_prints_help(capsys):
    assert main(["paper"]) == 2
    assert "solvability" in capsys.readouterr().out
