"""The one `flowcast` CLI: --version, choices in help (no Python type names), `forecast`,
checkpoints of the weekly forecast accepted by `estimate`/`rollout`, `smc filter --prior` with
dates kept, and one-line errors for bad cells, non-finite options and a directory as --out."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from flows.cli import app, build_command  # the entry point's module: every command
from pipeline.cli import package_version

REPO = Path(__file__).resolve().parents[1]
PYTHON_TYPE_LABELS = re.compile(r"<(int|str|float|bool|path)>|list\[|<int range>|<float range>")


@pytest.fixture(scope="module")
def cli():
    build_command()  # registers every command module
    runner = CliRunner()

    def invoke(*args: str):  # noqa: ANN202
        return runner.invoke(app, list(args), prog_name="flowcast",
                             env={"COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb"})

    return invoke


def _all_commands(command, path=()):  # noqa: ANN001, ANN202
    yield path
    for name, sub in getattr(command, "commands", {}).items():
        yield from _all_commands(sub, (*path, name))


def test_version(cli):
    result = cli("--version")
    assert result.exit_code == 0 and result.output.strip() == f"flowcast {package_version()}"
    assert package_version() == "0.1.0"


def test_help_shows_choices_and_no_python_type_names(cli):
    paths = list(_all_commands(build_command()))
    assert ("forecast",) in paths and ("smc", "filter") in paths and ("backtest",) not in paths \
        or ("backtest",) in paths  # `backtest` belongs to another change; either way is fine
    for path in paths:
        result = cli(*path, "--help")
        assert result.exit_code == 0, (path, result.output)
        assert not PYTHON_TYPE_LABELS.search(result.output), (path, result.output)
    train = cli("train", "--help").output
    assert "<mlp|transformer|transformer-ke|mamba>" in train and "<paper|fast>" in train
    assert "<forward|backward>" in train and "<nflows|zuko>" in train
    assert "sir-sf-joint|sf-waves-joint>" in train
    assert "<sir-single|sir-multi|sir-sf>" in cli("smc", "filter", "--help").output
    forecast = cli("forecast", "--help").output
    assert "<default|tiny>" in forecast and "<live|cache|import>" in forecast
    bad = cli("train", "sir-multi", "--encoder", "gru")
    assert bad.exit_code == 2 and "'gru' is not one of" in bad.output


def test_the_command_line_lists_its_commands_without_loading_the_engine():
    """``flowcast --help`` (every command module registered) loads neither torch nor Prefect
    nor matplotlib: the choices come from pipeline/names.py, each command loads the engine
    when it runs. It took 5 s when the choices imported torch."""
    import subprocess
    import sys

    # flows.cli attaches `forecast`; pipeline.cli.main is the console script's command without
    # its hard exit (flows.server_guard.exit_now)
    script = ("import sys\nimport flows.cli\nfrom pipeline.cli import main\n"
              "sys.argv = ['flowcast', '--help']\n"
              "try:\n    main()\nexcept SystemExit:\n    pass\n"
              "print('loaded:', sorted(m for m in ('torch', 'prefect', 'matplotlib') "
              "if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "simulate" in run.stdout and "forecast" in run.stdout
    assert run.stdout.strip().endswith("loaded: []"), run.stdout[-500:]


def test_the_command_lines_names_are_those_of_their_registries():
    """pipeline/names.py spells the choices; the registries that say what each means hold
    exactly those keys, in the same order (the order --help lists them in)."""
    from pipeline.forecast.config import FORECAST_PRESETS
    from pipeline.names import FORECAST_PRESET_NAMES, SIR_PRIOR_NAMES, TRAINING_SETUPS
    from pipeline.systems.sir import SIR_PRIORS
    from pipeline.training.presets import SETUPS

    assert TRAINING_SETUPS == tuple(SETUPS)
    assert SIR_PRIOR_NAMES == tuple(SIR_PRIORS)
    assert FORECAST_PRESET_NAMES == tuple(FORECAST_PRESETS)


def test_makefile_forecast_target_calls_flowcast_forecast():
    makefile = (REPO / "Makefile").read_text()
    assert "$(VENV)/bin/flowcast forecast $(FORECAST_ARGS)" in makefile
    assert "python -m flows.weekly_forecast" not in makefile


@pytest.mark.slow  # a fresh process imports the whole CLI and starts Prefect's temporary server
def test_forecast_without_data_fails_in_one_line(tmp_path):
    """`flowcast forecast` as a user runs it (a process); no cache, offline: exit 1 and one
    error line that names the fix, before any work."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "FLOWCAST_DATA_DIR": str(tmp_path / "empty"),
           "PREFECT_HOME": str(tmp_path / "prefect-home"), "PREFECT_API_URL": ""}
    run = subprocess.run([str(Path(sys.executable).with_name("flowcast")), "forecast",
                          "--preset", "tiny", "--data-source", "cache",
                          "--output-dir", str(tmp_path / "reports")],
                         env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 1
    errors = [line for line in run.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "flowcast data import" in errors[0], run.stderr[-2000:]
    assert not (tmp_path / "reports").exists() or not any((tmp_path / "reports").iterdir())
    # found before any work: no Prefect server was started (it would have made its home)
    assert not (tmp_path / "prefect-home").exists()


def test_an_empty_cache_is_named_before_any_work_for_sf_and_a_county(tmp_path, monkeypatch,
                                                                     datasf_dir):
    """The offline pre-flight (``require_offline_data``) raises the run's own error for San
    Francisco and for a county, and passes once the cache holds the data."""
    from pipeline.errors import OfflineError
    from pipeline.forecast.config import DataSourceConfig
    from pipeline.forecast.sources import import_exports, require_offline_data

    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "data"))
    with pytest.raises(OfflineError, match=r"no cached DataSF cases data .* No usable DataSF"):
        require_offline_data(DataSourceConfig(kind="cache"))
    with pytest.raises(OfflineError, match=r"no cached CDPH county data .* no forecast for "
                                           r"Los Angeles"):
        require_offline_data(DataSourceConfig(kind="cache", county="Los Angeles"))
    require_offline_data(DataSourceConfig(kind="live"))        # live: the fetch decides
    import_exports([str(datasf_dir)])
    require_offline_data(DataSourceConfig(kind="cache"))


# ------------------------------------------------------------------------------- smc filter


def _sf_like_csv(path: Path, *, dates: bool = True) -> pd.DataFrame:
    """30 days of an SF-sized epidemic (I ~ 1e-3) with observation noise 5e-4."""
    from pipeline.systems.sir import simulate_sir

    x0 = torch.tensor([[0.90, 1e-3, 0.099]], dtype=torch.float64)
    states = simulate_sir(x0, torch.tensor([0.15], dtype=torch.float64),
                          torch.tensor([0.1], dtype=torch.float64), 29, 1.0)[0].numpy()
    noise = np.random.default_rng(0).normal(0.0, 5e-4, states.shape)
    frame = pd.DataFrame(states + noise, columns=["S", "I", "R"])
    if dates:
        frame.insert(0, "date", pd.date_range("2022-01-01", periods=30).strftime("%Y-%m-%d"))
    else:
        frame.insert(0, "time", np.arange(30.0))
    frame.to_csv(path, index=False)
    return frame


def test_smc_filter_prior_by_name_keeps_dates(cli, tmp_path):
    source, out = tmp_path / "sf.csv", tmp_path / "filtered.csv"
    frame = _sf_like_csv(source)
    result = cli("smc", "filter", "--observations", str(source), "--out", str(out),
                 "--prior", "sir-sf", "--particles", "400")
    assert result.exit_code == 0, result.output
    assert "prior sir-sf: beta 0.0949, gamma 0.099, observation noise 0.0005, process noise " \
           "0.0001" in result.output
    written = pd.read_csv(out)
    assert written["date"].tolist() == frame["date"].tolist()
    assert written["time"].tolist() == list(np.arange(30.0))
    # SF-sized noise: the band around I is a few 1e-3 wide, not the paper's +-0.08
    width = (written["I_upper_3sigma"] - written["I_lower_3sigma"]).iloc[5:].median()
    assert width < 5e-3
    paper = cli("smc", "filter", "--observations", str(source), "--out", str(out),
                "--particles", "400")
    assert "prior sir-single: beta 0.03, gamma 0.01, observation noise 0.027" in paper.output
    wide = pd.read_csv(out)
    assert (wide["I_upper_3sigma"] - wide["I_lower_3sigma"]).iloc[5:].median() > 10 * width


def test_smc_filter_refuses_a_non_numeric_cell(cli, tmp_path):
    source = tmp_path / "obs.csv"
    frame = _sf_like_csv(source, dates=False).astype({"I": object})
    frame.loc[3, "S"] = np.nan  # empty cell: a missing observation, fine
    frame.loc[7, "I"] = "abc"
    frame.to_csv(source, index=False)
    result = cli("smc", "filter", "--observations", str(source), "--out", str(tmp_path / "o.csv"))
    assert result.exit_code == 2
    assert result.output.strip() == (f"error: {source}: row 8 (line 9), column 'I': 'abc' is not "
                                     "a finite number (leave the cell empty for a missing "
                                     "observation)")
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("option, bad, message", [
    ("--obs-sigma", "nan", "--obs-sigma must be a finite number, got nan"),
    ("--obs-sigma", "0", "--obs-sigma must be > 0, got 0"),
    ("--process-sigma", "-1e-3", "--process-sigma must be >= 0, got -0.001"),
    ("--beta", "inf", "--beta must be a finite number, got inf"),
    ("--param-jitter", "-1", "--param-jitter must be >= 0, got -1"),
])
def test_smc_filter_refuses_non_finite_or_negative_options(cli, tmp_path, option, bad, message):
    source = tmp_path / "obs.csv"
    _sf_like_csv(source)
    result = cli("smc", "filter", "--observations", str(source), "--out",
                 str(tmp_path / "o.csv"), option, bad)
    assert result.exit_code == 2 and message in result.output
    assert "Traceback" not in result.output and not (tmp_path / "o.csv").exists()


# -------------------------------------------------------------- forecast checkpoints in the CLI


@pytest.fixture(scope="module")
def forecast_store(tmp_path_factory):
    """The weekly forecast's own model pair (tiny preset), in its model store."""
    from pipeline.forecast import resolve_config
    from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models

    root = tmp_path_factory.mktemp("store")
    config = resolve_config("tiny")
    models = train_or_reuse_models(config, simulate_training_data(config), store_root=root)
    return models.path


def test_estimate_and_rollout_accept_the_forecast_checkpoints(cli, forecast_store, tmp_path):
    from pipeline.training.checkpoints import load_checkpoint

    forward = forecast_store / "forward" / "model.pt"
    extra = load_checkpoint(forward).meta.extra
    assert extra["preset"]["dataset"]["name"] == "sf-waves"  # the same metadata `train` writes
    assert extra["preset"]["dataset"]["direction"] == "forward"
    window = tmp_path / "window.csv"
    _sf_like_csv(window)
    out = tmp_path / "est.csv"
    result = cli("estimate", "--checkpoint", str(forward), "--window", str(window),
                 "--out", str(out), "--samples", "50")
    assert result.exit_code == 0, result.output
    samples = pd.read_csv(out)
    # the forecast's joint flows estimate (S, I, R, beta); gamma is the conversion's fixed 1/7
    assert list(samples.columns) == ["sample", "S", "I", "R", "beta"] and len(samples) == 50
    summary = pd.read_csv(tmp_path / "est_summary.csv")
    assert summary["date"].iloc[0] == "2022-01-31"  # one day after the window's last date
    rolled = cli("rollout", "--checkpoint", str(forecast_store / "backward" / "model.pt"),
                 "--series", str(window), "--out", str(tmp_path / "roll"), "--horizon", "3",
                 "--paths", "8")
    assert rolled.exit_code == 0, rolled.output
    assert "(backward)" in rolled.output
    assert pd.read_csv(tmp_path / "roll" / "summary.csv")["date"].min() == "2021-12-29"


def test_forecast_checkpoints_saved_before_the_preset_was_recorded_still_load(
        cli, forecast_store, tmp_path):
    """Older model-store entries lack extra['preset']: it is recovered from entry.json."""
    import shutil

    entry = tmp_path / "entry"
    shutil.copytree(forecast_store, entry)
    path = entry / "forward" / "model.pt"
    payload = torch.load(path, weights_only=True)
    del payload["extra"]["preset"]
    torch.save(payload, path)
    window = tmp_path / "window.csv"
    _sf_like_csv(window)
    result = cli("estimate", "--checkpoint", str(path), "--window", str(window),
                 "--out", str(tmp_path / "e.csv"), "--samples", "10")
    assert result.exit_code == 0, result.output
    (entry / "entry.json").unlink()
    orphan = cli("estimate", "--checkpoint", str(path), "--window", str(window),
                 "--out", str(tmp_path / "e.csv"), "--samples", "10")
    assert orphan.exit_code == 1 and "does not record its training dataset" in orphan.output


def test_estimate_out_existing_directory_is_a_clear_error(cli, forecast_store, tmp_path):
    window = tmp_path / "window.csv"
    _sf_like_csv(window)
    result = cli("estimate", "--checkpoint", str(forecast_store / "forward" / "model.pt"),
                 "--window", str(window), "--out", str(tmp_path))
    assert result.exit_code == 1
    assert result.output.strip() == (f"error: --out {tmp_path} is a directory; give the samples "
                                     f"CSV file to write (e.g. {tmp_path / 'estimate.csv'})")
    nan_time = cli("estimate", "--checkpoint", str(forecast_store / "forward" / "model.pt"),
                   "--window", str(window), "--out", str(tmp_path / "x.csv"),
                   "--target-time", "nan")
    assert nan_time.exit_code == 2 and "--target-time must be a finite number" in nan_time.output
