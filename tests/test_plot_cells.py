"""scripts/plot_cells.py: the per-task figure of several run directories, and its errors."""

import json

import pytest


def _run_dir(path, methods):
    path.mkdir()
    (path / "results.json").write_text(json.dumps({"methods": {
        m: {"iterations_to_success": its} for m, its in methods.items()}}))
    return path


def test_reads_each_cell_and_draws_one_panel_per_group(plot_cells, tmp_path):
    a = _run_dir(tmp_path / "a", {"comps": [[10, 20, 30], [12, 22, 34]]})
    b = _run_dir(tmp_path / "b", {"comps": [[1, 2, 3]], "ppo": [[4, 5, 6]]})
    label, its = plot_cells.read_cell(f"x={a}")
    assert label == "x" and its.shape == (2, 3) and its[:, 1:].mean() == 26.5
    assert plot_cells.read_cell(f"y={b}:ppo")[1].tolist() == [[4, 5, 6]]
    out = tmp_path / "f.png"
    assert plot_cells.main(["--out", str(out), "--panel", "A", f"x={a}", "--panel", "B", f"y={b}:ppo"]) == 0
    assert out.stat().st_size > 0


@pytest.mark.parametrize("spec, message", [
    ("nolabel", "expected LABEL=DIR"),
    ("x={missing}", "cannot read a run's results"),
    ("x={two}", "name one as"),
    ("x={two}:pnc", "has no method 'pnc'"),
])
def test_bad_cells_exit_2_naming_the_file(plot_cells, tmp_path, capsys, spec, message):
    two = _run_dir(tmp_path / "two", {"comps": [[1]], "ppo": [[2]]})
    spec = spec.format(missing=tmp_path / "nothing", two=two)
    assert plot_cells.main(["--out", str(tmp_path / "f.png"), "--panel", "A", spec]) == 2
    assert message in capsys.readouterr().err


def test_a_panel_without_cells_exits_2_naming_it(plot_cells, tmp_path, capsys):
    assert plot_cells.main(["--out", str(tmp_path / "f.png"), "--panel", "Empty"]) == 2
    assert "--panel 'Empty' has no LABEL=DIR" in capsys.readouterr().err
