"""pipeline.paper: the paper-table run as a package (flowcast reproduce tables, bench script)."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import torch

from pipeline.paper import BenchConfig, Locations, render_markdown, required_models
from pipeline.paper.cells import Cell, make_cell
from pipeline.paper.models import RequiredModel, bench_preset, trained_estimator
from pipeline.paper.published import PAPER
from pipeline.training.checkpoints import load_checkpoint

REPO = Path(__file__).resolve().parents[1]


def test_the_tables_have_the_papers_cells_and_need_19_models():
    assert sum(len(cells) for cells in PAPER.values()) == 60
    models = required_models()
    assert len(models) == 19 and len(set(models)) == 19
    assert models[0] == RequiredModel("vehicle", "transformer", "forward", "vehicle-full")


def test_bench_preset_applies_the_runs_sizes_and_budget():
    cfg = BenchConfig.quick_config()
    preset = bench_preset(RequiredModel("vehicle", "mamba", "backward", "vehicle-full"), cfg)
    assert preset.dataset.name == "vehicle-full" and preset.dataset.direction == "backward"
    assert preset.dataset.n_trajectories == 300 and preset.recipe == "fast"
    assert (preset.train.time_budget_s, preset.train.iterations, preset.train.eval_every) == (
        10.0, 40, 10)
    assert preset.train.seed == cfg.seed and preset.train.num_threads == torch.get_num_threads()
    full = bench_preset(RequiredModel("vehicle", "transformer", "forward"), BenchConfig())
    assert full.train.time_budget_s == 360.0 and full.dataset.name == "vehicle-dropout"
    sir = bench_preset(RequiredModel("sir-multi", "transformer-ke", "forward"), BenchConfig())
    assert sir.train.time_budget_s == 200.0 and sir.dataset.n_trajectories is None


def test_trained_estimator_trains_once_then_loads_the_cached_checkpoint(tmp_path, capsys):
    cfg = dataclasses.replace(BenchConfig.quick_config(), train_iterations=12,
                              n_trajectories={"sir-multi": 6})
    locations = Locations.under(tmp_path)
    model = RequiredModel("sir-multi", "mlp", "backward")
    first = trained_estimator(model, cfg, locations)
    run_name = "sir-multi-sir-multi-backward-mlp-zuko-fast-10s"
    checkpoint = tmp_path / "bench" / "work" / "quick" / run_name / "model.pt"
    assert f"training {run_name}" in capsys.readouterr().out
    extra = load_checkpoint(checkpoint).meta.extra
    assert extra["direction"] == "backward" and extra["preset"]["train"]["iterations"] == 12
    again = trained_estimator(model, cfg, locations)
    assert "training" not in capsys.readouterr().out
    context = torch.randn(3, 5, 4, generator=torch.Generator().manual_seed(1))
    mask = torch.ones(3, 5, dtype=torch.bool)
    eps = torch.randn(3, 7, first.features, generator=torch.Generator().manual_seed(2))
    assert torch.equal(first.noise_to_data(eps, context, mask),
                       again.noise_to_data(eps, context, mask))


def test_markdown_lists_every_table_and_the_collapsed_smc_windows():
    use = torch.tensor([True, True, False])
    smc: Cell = make_cell("Table 1", "At-bifurcation (fw)", "Sequential MC", 1.5, 0.2, 40.0, use)
    smc["collapsed_windows"] = 1
    cells = [make_cell("Table 1", "At-bifurcation (fw)", "Conditional NF", 0.5, 0.2, 40.0, use),
             smc]
    text = render_markdown(cells, BenchConfig.quick_config(), 12.0)
    assert all(f"## {table}" in text for table in PAPER)
    assert "| At-bifurcation (fw) | Conditional NF | 3.268 | 0.500 | 0.200 | 0.300 | 40 | 2/3 |" \
        in text
    assert ("*At-bifurcation (fw) / Sequential MC: 1 windows where the particle set "
            "collapsed") in text
    assert text.endswith("2 of 2 cells at or below the paper's value.\n")


def test_locations_show_figures_relative_to_the_root(tmp_path):
    locations = Locations.under(tmp_path)
    assert locations.display(locations.results / "figures" / "a.png") == \
        str(Path("bench/results/figures/a.png"))
    elsewhere = Locations(results=Path("/elsewhere"), work=tmp_path, root=tmp_path)
    assert elsewhere.display(elsewhere.results / "a.png") == "/elsewhere/a.png"


def test_reproduce_tables_needs_no_checkout(tmp_path):
    """The command imports pipeline.paper from the installed package: it runs from anywhere."""
    flowcast = Path(sys.executable).with_name("flowcast")
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb"}
    run = subprocess.run([str(flowcast), "reproduce", "tables", "--help"], cwd=tmp_path,
                         capture_output=True, text=True, env=env, timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    assert "--out" in run.stdout and "--work" in run.stdout and "--quick" in run.stdout
    source = (REPO / "pipeline" / "cli" / "reproduce.py").read_text()
    assert "sys.path" not in source and "from bench" not in source
