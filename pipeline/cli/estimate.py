"""`flowcast estimate` and `flowcast rollout`: estimates and rollouts from a CSV of observations.

CSV input: a ``time`` column (numbers) or a ``date`` column (ISO dates; time = days since the
first date), plus the system's observed columns (SIR: S, I, R; vehicle: p_x, p_y), one row per
observation, increasing in time.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import numpy as np
import pandas as pd
import typer

from pipeline.cli import app
from pipeline.cli.choices import Direction, finite
from pipeline.cli.choices import value as choice_value
from pipeline.cli.csv_input import read_timed_csv
from pipeline.errors import ConfigError, FlowcastError

if TYPE_CHECKING:
    from pipeline.inference.estimate import ModelInfo
    from pipeline.inference.rollout import RolloutResult
    from pipeline.models.estimator import ConditionalEstimator

_CHECKPOINT_HELP = ("model.pt of any flowcast model: `flowcast train`'s, or the weekly "
                    "forecast's (data/models/<key>/forward/model.pt)")


def read_observation_csv(path: Path, observed: tuple[str, ...]
                         ) -> tuple[np.ndarray, np.ndarray, pd.Series | None]:
    """(times (T,), values (T, C), dates or None); every observed value must be a number."""
    times, values, dates = read_timed_csv(path, observed)
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise ConfigError(f"{path}: non-numeric or missing values at rows "
                          f"{np.flatnonzero(bad)[:5].tolist()}")
    return times, values, dates


def _load(checkpoint: Path, direction: str | None
          ) -> tuple[ConditionalEstimator, ModelInfo, str]:
    """The checkpoint's estimator, its ModelInfo, and the direction (default: the model's own)."""
    from pipeline.inference.estimate import ModelInfo
    from pipeline.models.estimator import ConditionalEstimator
    from pipeline.training.checkpoints import load_checkpoint

    loaded = load_checkpoint(checkpoint)
    info = ModelInfo.from_checkpoint_extra(_with_preset(loaded.meta.extra, checkpoint),
                                           str(checkpoint))
    direction = direction or info.direction
    if direction != info.direction:
        raise ConfigError(f"{checkpoint} was trained for {info.direction} estimates; "
                          f"--direction {direction} needs a {direction} model")
    estimator = loaded.estimator
    assert isinstance(estimator, ConditionalEstimator)  # load_checkpoint rebuilds only these
    estimator.eval()
    return estimator, info, direction


def _with_preset(extra: dict[str, Any], checkpoint: Path) -> dict[str, Any]:
    """The checkpoint's metadata, with ``extra["preset"]`` recovered for weekly-forecast models
    saved before every trainer recorded it: their model-store entry
    (``<store>/<key>/entry.json``, beside ``<direction>/model.pt``) holds the presets."""
    import json

    if "preset" in extra:
        return extra
    entry = checkpoint.parent.parent / "entry.json"
    direction = extra.get("direction", checkpoint.parent.name)
    try:
        presets = json.loads(entry.read_text(encoding="utf-8"))["meta"]["config"]["presets"]
        return {**extra, "preset": presets[direction]}
    except (OSError, ValueError, KeyError, TypeError):
        return extra


def _check_out_file(out: Path) -> None:
    if out.is_dir():
        raise ConfigError(f"--out {out} is a directory; give the samples CSV file to write "
                          f"(e.g. {out / 'estimate.csv'})")


def _time_label(times: np.ndarray, dates: pd.Series | None
                ) -> dict[str, np.ndarray | pd.Index]:
    if dates is None:
        return {"time": times}
    return {"date": (dates.iloc[0] + pd.to_timedelta(times, unit="D")).strftime("%Y-%m-%d")}


def _fail(error: FlowcastError) -> NoReturn:
    typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=1) from error


@app.command("estimate")
def estimate_command(
    checkpoint: Annotated[Path, typer.Option(help=_CHECKPOINT_HELP)],
    window: Annotated[Path, typer.Option(help="CSV of the context observations (time or date "
                                              "column + the observed columns)")],
    out: Annotated[Path, typer.Option(help="samples CSV; the summary goes to <out>_summary.csv")],
    direction: Annotated[Direction | None, typer.Option(
        help="default: the model's training direction")] = None,
    target_time: Annotated[float | None, typer.Option(
        callback=finite(),
        help="time (or days after the first date) to estimate; default one step after the "
             "last row (forward) or before the first (backward)")] = None,
    samples: Annotated[int, typer.Option(min=2, help="number of samples")] = 1000,
    seed: Annotated[int, typer.Option(help="seed of the samples")] = 0,
) -> None:
    """Estimate the state at one time from a window of observations: samples + summary CSVs."""
    from pipeline.inference.estimate import ObservationWindow, estimate
    from pipeline.io import atomic_write_text

    try:
        _check_out_file(out)
        estimator, info, direction_name = _load(checkpoint, choice_value(direction))
        times, values, dates = read_observation_csv(window, info.observed_names)
        step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
        if target_time is None:
            target_time = float(times[-1] + step if direction_name == "forward"
                                else times[0] - step)
        result = estimate(estimator, ObservationWindow(times, values, target_time), direction_name,
                          samples, seed, names=info.target_names, window_length=info.window)
        sample_frame = pd.DataFrame(result.samples.double().numpy(), columns=list(result.names))
        sample_frame.insert(0, "sample", np.arange(len(sample_frame)))
        summary = pd.DataFrame(result.summary_rows())
        label = _time_label(np.array([target_time]), dates)
        for key, value in label.items():
            summary.insert(0, key, np.repeat(value, len(summary)))
        atomic_write_text(out, sample_frame.to_csv(index=False))
        summary_path = out.with_name(f"{out.stem}_summary.csv")
        atomic_write_text(summary_path, summary.to_csv(index=False))
    except FlowcastError as error:
        _fail(error)
    typer.echo(f"{samples} samples -> {out}; summary -> {summary_path}")


@app.command("rollout")
def rollout_command(
    checkpoint: Annotated[Path, typer.Option(help=_CHECKPOINT_HELP)],
    series: Annotated[Path, typer.Option(help="CSV of observations (time or date column + the "
                                              "observed columns)")],
    out: Annotated[Path, typer.Option(help="output directory")],
    horizon: Annotated[int, typer.Option(min=1, help="steps to roll out past the series' end "
                                                     "(forward) or before its start (backward)")]
    = 28,
    window_every: Annotated[int | None, typer.Option(
        min=1, help="also re-anchor on the observed series every W steps (rolling windows; the "
                    "paper uses 7 and 28) and write bands over the whole series")] = None,
    paths: Annotated[int, typer.Option(min=2, help="sample paths")] = 200,
    direction: Annotated[Direction | None, typer.Option(
        help="default: the model's training direction")] = None,
    feedback_noise: Annotated[float | None, typer.Option(
        callback=finite(0.0),
        help="σ of the noise added to fed-back predictions (default: the training data's "
             "observation noise; 0 feeds back the bare state)")] = None,
    seed: Annotated[int, typer.Option(help="seed of the paths")] = 0,
) -> None:
    """Roll the model out from a series (paths.csv, summary.csv; rolling.csv with --window-every)."""
    from pipeline.inference.estimate import ObservationWindow
    from pipeline.io import atomic_write_text
    from pipeline.inference.rollout import RolloutConfig, rolling_rollout, rollout

    try:
        if out.exists() and not out.is_dir():
            raise ConfigError(f"--out {out} is a file; rollout writes a directory")
        estimator, info, direction_name = _load(checkpoint, choice_value(direction))
        times, values, dates = read_observation_csv(series, info.observed_names)
        if len(times) < info.window:
            raise ConfigError(f"{series}: {len(times)} rows, the model needs at least "
                              f"{info.window}")
        step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
        sigma = info.obs_sigma if feedback_noise is None else feedback_noise
        config = RolloutConfig(n_paths=paths, feedback_noise_sigma=sigma, seed=seed)
        if direction_name == "forward":
            window = ObservationWindow(times[-info.window:], values[-info.window:],
                                       times[-1] + step)
        else:
            window = ObservationWindow(times[:info.window], values[:info.window], times[0] - step)
        result = rollout(estimator, window, horizon, step, direction_name, config,
                         names=info.target_names, window_length=info.window)
        out.mkdir(parents=True, exist_ok=True)
        _write_rollout(result, dates, out / "summary.csv", out / "paths.csv")
        written = ["summary.csv", "paths.csv"]
        if window_every is not None:
            rolling = rolling_rollout(estimator, times, values, window_every, direction_name,
                                      config, names=info.target_names, window_length=info.window)
            _write_rollout(rolling, dates, out / "rolling.csv", None)
            written.append("rolling.csv")
    except FlowcastError as error:
        _fail(error)
    typer.echo(f"{paths} paths x {horizon} steps ({direction_name}) -> {out}: "
               f"{', '.join(written)}")


def _write_rollout(result: RolloutResult, dates: pd.Series | None, summary_path: Path,
                   paths_path: Path | None) -> None:
    from pipeline.io import atomic_write_text

    summary = result.summary_frame()
    label = _time_label(summary["time"].to_numpy(), dates)
    summary = summary.drop(columns="time")
    for key, value in label.items():
        summary.insert(0, key, value)
    atomic_write_text(summary_path, summary.to_csv(index=False))
    if paths_path is None:
        return
    n_paths, n_steps, dim = result.samples.shape
    frame = pd.DataFrame(result.samples.reshape(-1, dim).double().numpy(), columns=list(result.names))
    frame.insert(0, "path", np.repeat(np.arange(n_paths), n_steps))
    for key, value in _time_label(np.tile(result.times, n_paths), dates).items():
        frame.insert(1, key, value)
    atomic_write_text(paths_path, frame.to_csv(index=False))
