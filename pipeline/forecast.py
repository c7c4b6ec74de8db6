"""The weekly San Francisco forecast as plain library steps (the Prefect flow only wraps them).

Steps, each a function here so it can be called, tested and timed without Prefect:

1. :func:`load_series` — DataSF cases/deaths/tests (live with cache fallback, cache only, or
   imported CSV exports), trimmed of the last days still under revision;
   :func:`series_to_sir` — S, I, R proportions (``pipeline.data.sir_transform``).
2. :func:`simulate_training_data` — the synthetic ``sir-multi`` ensemble (β ~ U[0.02, 0.04],
   γ ~ U[0.005, 0.025], the paper's COVID-19 section) cut into forward and backward windows whose
   target is the joint (S, I, R, β, γ) — the paper's "joint state and parameter estimation".
3. :func:`train_or_reuse_models` — train the forward and backward estimators, or reuse the cached
   pair (:mod:`pipeline.model_store`, key = training config + training-data hash).
4. :func:`latest_estimates` — forward estimate of the day after the last observation and backward
   estimate of the day before the last window (both from the latest R observations).
5. :func:`rollouts` — rolling rollouts re-anchored every 7 and 28 days, forward and backward
   (``pipeline.rollout``), plus :func:`future_paths`: forward sample paths past the last observed
   day, the forecast proper (hub CSV, 1–4 weeks).
6. :func:`parameter_track` — β, γ over time (posterior mean and 95 % interval per day).
7. :func:`nll_table` — the paper's Table 5: mean NLL of the observed state under the flow's state
   marginal at random days along the SF trajectory (forward / backward).
8. :func:`seeded_smc` — the paper's hybrid: particles drawn from the forward joint estimate seed a
   bootstrap filter over the following observations; 3σ bands.

Reading of the paper: the context window R = 5 ("five-observation context"); rollouts and the
joint estimates use the transformer encoder in the paper; here the encoder is a parameter.
Every random step draws from a generator seeded by ``ForecastConfig.seed`` plus a fixed per-step
offset, so the same seed, data and model give the same numbers.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from pipeline.errors import ConfigError, OfflineError
from pipeline.progress import ProgressReporter

log = logging.getLogger(__name__)

DataSourceKind = Literal["live", "cache", "import"]
STATE_NAMES = ("S", "I", "R")
JOINT_NAMES = ("S", "I", "R", "beta", "gamma")
DIRECTIONS = ("forward", "backward")
# Per-step seed offsets: changing one step's draws never shifts another's.
_SEED_OFFSETS = {"simulate": 0, "train_forward": 11, "train_backward": 12, "latest": 21,
                 "rollout": 31, "future": 41, "params": 51, "nll": 61, "smc": 71}


@dataclass(frozen=True)
class DataSourceConfig:
    """Where the SF series comes from.

    ``live``: fetch DataSF (HTTP retries with backoff inside the client), falling back to the cache
    with a staleness note; ``cache``: offline, cache only; ``import``: import the given DataSF CSV
    exports into the cache (``flowcast data import``), then read it offline.
    """

    kind: DataSourceKind = "live"
    import_paths: tuple[str, ...] = ()
    http_retries: int = 3          # per HTTP request, exponential backoff inside the client
    http_backoff_s: float = 2.0
    task_retries: int = 2          # whole-fetch retries by the orchestrator (live only)
    task_retry_delay_s: float = 10.0

    def __post_init__(self) -> None:
        if self.kind not in ("live", "cache", "import"):
            raise ConfigError(f"data source must be live, cache or import, got {self.kind!r}")
        if self.kind == "import" and not self.import_paths:
            raise ConfigError("data source 'import' needs import_paths (DataSF CSV exports)")


@dataclass(frozen=True)
class ForecastConfig:
    """Everything that determines one weekly run (with the data and the seed)."""

    preset: str = "default"
    training_preset: str = "sir-joint"
    recipe: str = "fast"
    encoder: str | None = None            # None: transformer (the paper's SF runs)
    n_trajectories: int = 500             # synthetic sir-multi ensemble size
    horizon_days: int | None = None       # None: the prior's 1000 days
    train_iterations: int | None = None   # None: the recipe's
    window: int = 5                       # R, the paper's five-observation context
    rollout_windows: tuple[int, ...] = (7, 28)
    rollout_paths: int = 200
    forecast_days: int = 28               # future paths: 4 weeks for the hub CSV
    hub_paths: int = 200
    n_samples: int = 1000                 # draws per estimate
    parameter_stride_days: int = 1
    nll_locations: int = 100
    smc_particles: int = 1000
    smc_days: int = 56                    # observations the seeded filter runs over
    trailing_days: int = 14
    seed: int = 0
    data: DataSourceConfig = field(default_factory=DataSourceConfig)

    def __post_init__(self) -> None:
        if self.window < 1 or any(w < 1 for w in self.rollout_windows):
            raise ConfigError(f"window={self.window} and rollout_windows={self.rollout_windows} "
                              "must be >= 1")
        for name in ("n_trajectories", "rollout_paths", "forecast_days", "hub_paths", "n_samples",
                     "parameter_stride_days", "nll_locations", "smc_particles", "smc_days"):
            if getattr(self, name) < 1:
                raise ConfigError(f"ForecastConfig.{name}={getattr(self, name)} must be >= 1")

    def step_seed(self, step: str) -> int:
        return self.seed * 1000 + _SEED_OFFSETS[step]

    def training_identity(self) -> dict[str, Any]:
        """What determines the trained models (the model-cache key is built from this)."""
        return {"training_preset": self.training_preset, "recipe": self.recipe,
                "encoder": self.encoder, "n_trajectories": self.n_trajectories,
                "horizon_days": self.horizon_days, "train_iterations": self.train_iterations,
                "window": self.window, "seed": self.seed}


FORECAST_PRESETS: dict[str, ForecastConfig] = {
    # The product: sir-joint on the full synthetic ensemble with the fast recipe (fits the
    # 15-minute budget on 2 cores; `recipe="paper"` is the paper's 10k iterations).
    "default": ForecastConfig(preset="default"),
    # Seconds, for tests and smoke runs: small ensemble, short horizon, few iterations/samples.
    "tiny": ForecastConfig(preset="tiny", recipe="fast", encoder="mlp", n_trajectories=24,
                           horizon_days=200, train_iterations=20, rollout_paths=16,
                           forecast_days=28, hub_paths=200, n_samples=128,
                           parameter_stride_days=7, nll_locations=20, smc_particles=200,
                           smc_days=28,
                           data=DataSourceConfig(http_retries=2, http_backoff_s=0.0,
                                                 task_retries=1, task_retry_delay_s=0.0)),
}


def resolve_config(preset: str, **overrides: Any) -> ForecastConfig:
    """The named preset with ``overrides`` (None values are ignored) — the CLI/flow edge."""
    try:
        base = FORECAST_PRESETS[preset]
    except KeyError:
        raise ConfigError(f"unknown forecast preset {preset!r}; known: "
                          f"{sorted(FORECAST_PRESETS)}") from None
    return dataclasses.replace(base, **{k: v for k, v in overrides.items() if v is not None})


# --------------------------------------------------------------------------------------- data


def import_exports(paths: Sequence[str], *, if_empty: bool = False) -> list[Any]:
    """``flowcast data import`` as a function: validate and cache DataSF CSV exports."""
    from pipeline.data.csv_import import import_csv_exports

    files = _expand_import_paths(paths)
    return import_csv_exports(files, if_empty=if_empty)


def _expand_import_paths(paths: Sequence[str]) -> list[Path]:
    """Files as given; a directory contributes its cases/deaths/tests exports (by column match)."""
    from pipeline.data.csv_import import detect_dataset, read_csv_bytes

    out: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_file():
            out.append(path)
        elif path.is_dir():
            found: dict[str, Path] = {}
            for candidate in sorted(path.rglob("*.csv")):
                try:
                    head = read_csv_bytes(candidate.read_bytes()[:4096].rsplit(b"\n", 1)[0],
                                          source=str(candidate))
                    key = detect_dataset(list(head.columns), source=str(candidate)).key
                except Exception:  # noqa: BLE001 - not a DataSF export we know: skip it
                    continue
                found.setdefault(key, candidate)
            out.extend(found.values())
        else:
            raise ConfigError(f"import path {path} does not exist")
    if not out:
        raise ConfigError(f"no DataSF CSV exports found in {list(paths)}")
    return out


def load_series(config: ForecastConfig, *, session: Any = None) -> Any:
    """The SF series per ``config.data``; see :class:`DataSourceConfig`. Returns ``SFSeries``."""
    from pipeline.data.datasf import ClientConfig
    from pipeline.data.series import SFDataConfig, load_sf_series

    source = config.data
    client = ClientConfig(max_retries=source.http_retries, backoff_base_s=source.http_backoff_s)
    data_config = SFDataConfig(trailing_days=config.trailing_days, client=client)
    if source.kind == "import":
        summaries = import_exports(source.import_paths)
        log.info("imported %s", ", ".join(f"{s.dataset_key} ({s.row_count} rows)"
                                          for s in summaries))
    try:
        return load_sf_series(data_config, offline=source.kind != "live", session=session)
    except OfflineError as exc:
        raise OfflineError(f"{exc} No usable DataSF data, so no forecast was made; the last good "
                           "report is unchanged. Import the exports with `flowcast data import "
                           "FILE...` (or run with data source 'import').") from exc


def data_is_stale(series: Any, source: DataSourceKind) -> bool:
    """True when a live fetch was asked for but the cache had to be used."""
    return source == "live" and any(p.from_cache for p in series.provenance.datasets)


def staleness_notes(series: Any) -> list[str]:
    return [f"{p.dataset_key}: {note}" for p in series.provenance.datasets for note in p.notes]


def series_to_sir(series: Any) -> Any:
    """S, I, R proportions (``SIRSeries``) with the default conversion (see sir_transform)."""
    from pipeline.data.sir_transform import to_sir

    return to_sir(series)


def sir_arrays(sir_frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, pd.DatetimeIndex]:
    """(times in days since the first date (T,), values (T, 3), dates) of an S/I/R frame."""
    dates = pd.DatetimeIndex(pd.to_datetime(sir_frame["date"]))
    times = ((dates - dates[0]) / pd.Timedelta(days=1)).to_numpy(dtype=np.float64)
    values = sir_frame[list(STATE_NAMES)].to_numpy(dtype=np.float64)
    return times, values, dates


# --------------------------------------------------------------------------- training data


@dataclass(frozen=True)
class TrainingData:
    """Forward and backward (train, validation) windowed datasets and their combined hash."""

    splits: dict[str, tuple[Any, Any]]
    data_sha256: str
    n_trajectories: int


def simulate_training_data(config: ForecastConfig,
                           progress: ProgressReporter | None = None) -> TrainingData:
    from pipeline.datasets import dataset_sha256, train_validation_split, windows_from_sir
    from pipeline.io import sha256_bytes
    from pipeline.systems.sir import get_prior, simulate_ensemble

    prior = get_prior("sir-multi")
    if config.horizon_days is not None:
        prior = dataclasses.replace(prior, horizon_days=config.horizon_days)
    ensemble = simulate_ensemble(prior, config.n_trajectories, seed=config.step_seed("simulate"),
                                 progress=progress)
    splits, hashes = {}, []
    for direction in DIRECTIONS:
        ds = windows_from_sir(ensemble, direction=direction, target="state+params",
                              window=config.window)
        hashes.append(dataset_sha256(ds))
        splits[direction] = train_validation_split(ds)
    return TrainingData(splits=splits, data_sha256=sha256_bytes("|".join(hashes).encode()),
                        n_trajectories=ensemble.n_trajectories)


# -------------------------------------------------------------------------------- models


@dataclass(frozen=True)
class TrainedModels:
    forward: Any
    backward: Any
    key: str
    reused: bool
    path: Path
    histories: dict[str, list[dict[str, Any]]]
    best_val_nll: dict[str, float]
    encoder: str

    def by_direction(self, direction: str) -> Any:
        return self.forward if direction == "forward" else self.backward


def model_store_root() -> Path:
    from pipeline.data.cache import data_dir

    return data_dir() / "models"


def train_or_reuse_models(config: ForecastConfig, data: TrainingData, *, retrain: bool = False,
                          store_root: Path | None = None,
                          progress: ProgressReporter | None = None) -> TrainedModels:
    """Forward + backward joint estimators, from the cache unless config/data changed."""
    from pipeline.checkpoints import load_checkpoint
    from pipeline.model_store import ModelStore

    store = ModelStore(store_root or model_store_root())

    def build(out_dir: Path) -> dict[str, Any]:
        best = {}
        for direction in DIRECTIONS:
            best[direction] = _train_direction(config, data, direction, out_dir / direction,
                                               progress)
        return {"best_val_nll": best}

    entry = store.get_or_build(config.training_identity(), data.data_sha256, build,
                               retrain=retrain)
    loaded = {d: load_checkpoint(entry.path / d / "model.pt") for d in DIRECTIONS}
    for model in loaded.values():
        model.estimator.eval()
    encoder = _encoder_name(loaded["forward"].config)
    return TrainedModels(
        forward=loaded["forward"].estimator, backward=loaded["backward"].estimator,
        key=entry.key, reused=entry.reused, path=entry.path,
        histories={d: list(loaded[d].meta.history) for d in DIRECTIONS},
        best_val_nll={d: float(loaded[d].meta.extra.get("best_val_nll_original", float("nan")))
                      for d in DIRECTIONS},
        encoder=encoder)


def _encoder_name(estimator_config: Any) -> str:
    encoder = getattr(estimator_config, "encoder", None)
    return str(getattr(encoder, "kind", None) or getattr(encoder, "name", None) or encoder)


@dataclass(frozen=True)
class TrainingPlan:
    estimator: Any   # pipeline.models.estimator.EstimatorConfig
    train: Any       # pipeline.training.TrainConfig


# Recipes for the weekly joint model. "paper": the paper's training section (Adam 1e-3, 10,000
# iterations, batch 2,048, context noise 0.01 for SIR). "fast": fewer, smaller steps so a
# from-scratch weekly run with the transformer encoder fits 15 minutes on 2 cores.
_RECIPES = {"paper": {"iterations": 10_000, "batch_size": 2048},
            "fast": {"iterations": 3_000, "batch_size": 512}}
_SIR_CONTEXT_NOISE = 0.01


def training_plan(config: ForecastConfig) -> TrainingPlan:
    """Estimator + training config of the joint (S, I, R, β, γ) model for ``config``."""
    from pipeline.models.encoders import EncoderConfig
    from pipeline.models.estimator import make_estimator_config
    from pipeline.training import TrainConfig

    if config.recipe not in _RECIPES:
        raise ConfigError(f"unknown recipe {config.recipe!r}; known: {sorted(_RECIPES)}")
    recipe = dict(_RECIPES[config.recipe])
    if config.train_iterations is not None:
        recipe["iterations"] = config.train_iterations
    encoder = EncoderConfig(kind=config.encoder or "transformer")
    estimator = make_estimator_config(len(JOINT_NAMES), len(STATE_NAMES) + 1, config.window,
                                      encoder)
    train = TrainConfig(**recipe, eval_every=max(1, min(100, recipe["iterations"] // 4)),
                        context_noise_sigma=_SIR_CONTEXT_NOISE)
    return TrainingPlan(estimator, train)


def _train_direction(config: ForecastConfig, data: TrainingData, direction: str, out_dir: Path,
                     progress: ProgressReporter | None) -> float:
    from pipeline.models.estimator import build_estimator
    from pipeline.training import train_and_save

    plan = training_plan(config)
    seed = config.step_seed(f"train_{direction}")
    train_config = dataclasses.replace(plan.train, seed=seed)
    train_ds, val_ds = data.splits[direction]
    estimator = build_estimator(plan.estimator, train_ds.stats, seed=seed)
    result = train_and_save(estimator, train_ds, val_ds, train_config, None, out_dir,
                            estimator_config=plan.estimator, progress=progress,
                            extra={"direction": direction, "forecast_preset": config.preset})
    log.info("trained %s model: best validation NLL %.3f at iteration %d (%s)", direction,
             result.best_val_nll_original, result.best_iteration, result.stop_reason)
    return float(result.best_val_nll_original)


# ------------------------------------------------------------------------------ estimates


def _window(times: np.ndarray, values: np.ndarray, rows: slice, target_time: float) -> Any:
    from pipeline.estimate import ObservationWindow

    return ObservationWindow(times=times[rows], values=values[rows], target_time=float(target_time))


@dataclass(frozen=True)
class LatestEstimates:
    """Summaries of the latest forward (next day) and backward (day before the window) estimates."""

    table: pd.DataFrame  # direction, date, component, mean, std, q0.025, q0.5, q0.975
    samples: dict[str, Tensor]
    dates: dict[str, str]


def latest_estimates(models: TrainedModels, sir_frame: pd.DataFrame,
                     config: ForecastConfig) -> LatestEstimates:
    from pipeline.estimate import estimate

    times, values, dates = sir_arrays(sir_frame)
    r = config.window
    last = slice(len(times) - r, len(times))
    targets = {"forward": times[-1] + 1.0, "backward": times[-r] - 1.0}
    rows, samples, target_dates = [], {}, {}
    for direction in DIRECTIONS:
        est = estimate(models.by_direction(direction),
                       _window(times, values, last, targets[direction]), direction,
                       n_samples=config.n_samples, seed=config.step_seed("latest"),
                       names=JOINT_NAMES, window_length=r)
        date = dates[0] + pd.Timedelta(days=float(targets[direction]))
        target_dates[direction] = str(date.date())
        samples[direction] = est.samples
        rows += _summary_rows(est.samples.double(), direction, target_dates[direction])
    return LatestEstimates(pd.DataFrame(rows), samples, target_dates)


def _summary_rows(samples: Tensor, direction: str, date: str) -> list[dict[str, Any]]:
    q = torch.quantile(samples, torch.tensor([0.025, 0.5, 0.975], dtype=samples.dtype), dim=0)
    return [{"direction": direction, "date": date, "component": name,
             "mean": float(samples[:, d].mean()), "std": float(samples[:, d].std()),
             "q0.025": float(q[0, d]), "q0.5": float(q[1, d]), "q0.975": float(q[2, d])}
            for d, name in enumerate(JOINT_NAMES)]


def rollouts(models: TrainedModels, sir_frame: pd.DataFrame, config: ForecastConfig,
             progress: ProgressReporter | None = None) -> dict[tuple[str, int], Any]:
    """Rolling rollouts re-anchored every W days (W in ``rollout_windows``), fw and bw."""
    from pipeline.rollout import RolloutConfig, rolling_rollout

    times, values, _ = sir_arrays(sir_frame)
    out = {}
    for direction in DIRECTIONS:
        for every in config.rollout_windows:
            rc = RolloutConfig(n_paths=config.rollout_paths, feedback_noise_sigma=_obs_sigma(),
                               seed=config.step_seed("rollout") + every)
            out[(direction, every)] = rolling_rollout(
                models.by_direction(direction), times, values, every, direction, rc,
                names=JOINT_NAMES, window_length=config.window, progress=progress)
    return out


def _obs_sigma() -> float:
    from pipeline.systems.sir import get_prior

    return get_prior("sir-multi").obs_sigma


@dataclass(frozen=True)
class FuturePaths:
    dates: pd.DatetimeIndex
    samples: Tensor          # (P, H, 5): S, I, R, beta, gamma
    reference_date: dt.date


def future_paths(models: TrainedModels, sir_frame: pd.DataFrame,
                 config: ForecastConfig) -> FuturePaths:
    """Forward sample paths for ``forecast_days`` days after the last observed day."""
    from pipeline.rollout import RolloutConfig, rollout

    times, values, dates = sir_arrays(sir_frame)
    r = config.window
    window = _window(times, values, slice(len(times) - r, len(times)), times[-1] + 1.0)
    rc = RolloutConfig(n_paths=config.hub_paths, feedback_noise_sigma=_obs_sigma(),
                       seed=config.step_seed("future"))
    result = rollout(models.forward, window, config.forecast_days, 1.0, "forward", rc,
                     names=JOINT_NAMES, window_length=r)
    future_dates = pd.date_range(dates[-1] + pd.Timedelta(days=1), periods=config.forecast_days,
                                 freq="D")
    return FuturePaths(future_dates, result.samples, dates[-1].date())


def parameter_track(models: TrainedModels, sir_frame: pd.DataFrame,
                    config: ForecastConfig) -> pd.DataFrame:
    """β, γ (and the state) per day from the R observations before (fw) / after (bw) the day.

    Long table: direction, date, component, mean, std, q0.025, q0.5, q0.975; one flow call per
    direction for all days at once.
    """
    from pipeline.estimate import batch_window_context, sample_conditional

    times, values, dates = sir_arrays(sir_frame)
    r = config.window
    frames = []
    for direction in DIRECTIONS:
        targets = (np.arange(r, len(times), config.parameter_stride_days) if direction == "forward"
                   else np.arange(0, len(times) - r, config.parameter_stride_days))
        rows = [slice(t - r, t) if direction == "forward" else slice(t + 1, t + 1 + r)
                for t in targets]
        windows = [_window(times, values, s, times[t]) for s, t in zip(rows, targets, strict=True)]
        context, mask = batch_window_context(windows, direction, r)
        samples = sample_conditional(models.by_direction(direction), context, mask,
                                     config.n_samples, config.step_seed("params")).double()
        levels = torch.tensor([0.025, 0.5, 0.975], dtype=torch.float64)
        q = torch.quantile(samples, levels, dim=1)                                  # (3, B, D)
        for d, name in enumerate(JOINT_NAMES):
            frames.append(pd.DataFrame({
                "direction": direction, "date": dates[targets].strftime("%Y-%m-%d"),
                "component": name, "mean": samples[:, :, d].mean(1).numpy(),
                "std": samples[:, :, d].std(1).numpy(), "q0.025": q[0, :, d].numpy(),
                "q0.5": q[1, :, d].numpy(), "q0.975": q[2, :, d].numpy()}))
    return pd.concat(frames, ignore_index=True)


def nll_table(models: TrainedModels, sir_frame: pd.DataFrame, config: ForecastConfig,
              variant: str | None = None) -> pd.DataFrame:
    """Mean NLL of the observed (S, I, R) at ``nll_locations`` random days, fw and bw.

    The joint flow models (S, I, R, β, γ); the true β, γ of SF are unknown, so we score the
    *state marginal*: a Gaussian KDE (``metrics.kde_log_prob``) of the flow's (S, I, R) draws,
    evaluated at the observed state — the paper's "NLL of the estimated conditional density given
    the true state", aggregated across compartments (one joint 3-D density).
    """
    from pipeline.estimate import batch_window_context, sample_conditional
    from pipeline.metrics import kde_log_prob, mean_nll

    times, values, _ = sir_arrays(sir_frame)
    r = config.window
    generator = np.random.default_rng(config.step_seed("nll"))
    rows = []
    for direction in DIRECTIONS:
        candidates = (np.arange(r, len(times)) if direction == "forward"
                      else np.arange(0, len(times) - r))
        targets = np.sort(generator.choice(candidates, size=min(config.nll_locations,
                                                                len(candidates)), replace=False))
        slices = [slice(t - r, t) if direction == "forward" else slice(t + 1, t + 1 + r)
                  for t in targets]
        windows = [_window(times, values, s, times[t]) for s, t in zip(slices, targets, strict=True)]
        context, mask = batch_window_context(windows, direction, r)
        samples = sample_conditional(models.by_direction(direction), context, mask,
                                     config.n_samples, config.step_seed("nll")).double()
        log_p = kde_log_prob(samples[..., :3], torch.as_tensor(values[targets]))
        rows.append({"direction": direction, "variant": variant or models.encoder,
                     "locations": len(targets), "mean_nll": mean_nll(log_p.numpy())})
    return pd.DataFrame(rows)


def seeded_smc(models: TrainedModels, sir_frame: pd.DataFrame, config: ForecastConfig) -> Any:
    """NF-seeded SMC over the last ``smc_days`` days: flow draws at the first day seed it."""
    from pipeline.estimate import sample_conditional, window_context
    from pipeline.smc import SMCConfig, seeded_filter
    from pipeline.smc_models import SIRParamsModel

    times, values, dates = sir_arrays(sir_frame)
    r = config.window
    start = max(r, len(times) - config.smc_days)
    window = _window(times, values, slice(start - r, start), times[start])
    context, mask = window_context(window, "forward", r)
    particles = sample_conditional(models.forward, context, mask, config.smc_particles,
                                   config.step_seed("smc")).double()                # (1, N, 5)
    particles[..., :3] = particles[..., :3].clamp_min(0.0)
    particles[..., :3] /= particles[..., :3].sum(-1, keepdim=True)
    particles[..., 3:] = particles[..., 3:].clamp_min(0.0)
    model = SIRParamsModel.create(prior_mean=torch.as_tensor(values[start]))
    observations = torch.as_tensor(values[start:])[None]
    result = seeded_filter(particles, observations, model,
                           SMCConfig(num_particles=config.smc_particles,
                                     seed=config.step_seed("smc")),
                           times=torch.as_tensor(times[start:]))
    return SMCRun(result=result, dates=dates[start:])


@dataclass(frozen=True)
class SMCRun:
    result: Any
    dates: pd.DatetimeIndex

    def band_frame(self, n_sigma: float = 3.0) -> pd.DataFrame:
        lower, upper = self.result.sigma_band(n_sigma)
        frames = []
        for d, name in enumerate(self.result.state_names):
            frames.append(pd.DataFrame({
                "date": self.dates.strftime("%Y-%m-%d"), "component": name,
                "mean": self.result.mean[0, :, d].numpy(),
                f"lower_{n_sigma:g}sigma": lower[0, :, d].numpy(),
                f"upper_{n_sigma:g}sigma": upper[0, :, d].numpy()}))
        return pd.concat(frames, ignore_index=True)


# ------------------------------------------------------------------------------- outputs


@dataclass(frozen=True)
class ForecastResults:
    config: ForecastConfig
    sir_frame: pd.DataFrame
    vintage: str
    stale: bool
    stale_notes: tuple[str, ...]
    models: TrainedModels
    latest: LatestEstimates
    rollouts: dict[tuple[str, int], Any]
    future: FuturePaths
    parameters: pd.DataFrame
    nll: pd.DataFrame
    smc: SMCRun


def write_tables(results: ForecastResults, out_dir: Path) -> list[str]:
    """CSV tables + hub CSV + results.json into ``out_dir``; returns the file names written."""
    from pipeline.forecast_hub import HubConfig, hub_forecast_frame, write_hub_csv
    from pipeline.io import atomic_write_json, atomic_write_text

    out_dir.mkdir(parents=True, exist_ok=True)
    tables = {"sir_series.csv": results.sir_frame.assign(
                  date=pd.to_datetime(results.sir_frame["date"]).dt.strftime("%Y-%m-%d")),
              "latest_estimates.csv": results.latest.table,
              "parameter_estimates.csv": results.parameters,
              "nll_table.csv": results.nll,
              "smc_bands.csv": results.smc.band_frame(3.0)}
    for (direction, every), roll in results.rollouts.items():
        tables[f"rollout_{direction}_{every}d.csv"] = roll.summary_frame()
    for name, frame in tables.items():
        atomic_write_text(out_dir / name, frame.to_csv(index=False))
    hub = hub_forecast_frame(results.future.samples[..., :3].double().numpy(),
                             results.future.dates, results.future.reference_date,
                             HubConfig(n_sample_paths=min(200, results.config.hub_paths)))
    write_hub_csv(hub, out_dir / "hub_forecast.csv")
    summary = results_summary(results)
    atomic_write_json(out_dir / "results.json", summary)
    return sorted(list(tables) + ["hub_forecast.csv", "results.json"])


def results_summary(results: ForecastResults) -> dict[str, Any]:
    latest = results.latest.table
    fw = latest[latest["direction"] == "forward"].set_index("component")
    return {"reference_date": str(results.future.reference_date),
            "data_vintage": results.vintage, "data_stale": results.stale,
            "stale_notes": list(results.stale_notes), "model_key": results.models.key,
            "model_reused": results.models.reused, "encoder": results.models.encoder,
            "forward_next_day": {c: {"mean": float(fw.loc[c, "mean"]),
                                     "q0.025": float(fw.loc[c, "q0.025"]),
                                     "q0.975": float(fw.loc[c, "q0.975"])} for c in fw.index},
            "nll": results.nll.to_dict(orient="records"),
            "config": dataclasses.asdict(results.config)}


def write_report(results: ForecastResults, out_dir: Path) -> list[str]:
    """The HTML (and PDF) report via ``pipeline.report`` when it is installed, else a plain
    self-contained HTML page with the stale-data banner, provenance and the tables."""
    try:
        from pipeline.report import build_forecast_report  # the reports issue's renderer
    except ImportError:
        build_forecast_report = None
    if build_forecast_report is not None:
        return list(build_forecast_report(results, out_dir))
    return [_write_basic_report(results, out_dir)]


def _write_basic_report(results: ForecastResults, out_dir: Path) -> str:
    import html

    from pipeline.io import atomic_write_text

    banner = ""
    if results.stale:
        notes = "<br>".join(html.escape(n) for n in results.stale_notes)
        banner = (f'<p class="stale"><strong>Stale data:</strong> DataSF could not be reached; '
                  f"this forecast uses cached data.<br>{notes}</p>")
    latest = results.latest.table.to_html(index=False, float_format=lambda v: f"{v:.5g}")
    nll = results.nll.to_html(index=False, float_format=lambda v: f"{v:.4f}")
    params = results.parameters[results.parameters["component"].isin(["beta", "gamma"])]
    params = params.groupby(["direction", "component"]).tail(5).to_html(
        index=False, float_format=lambda v: f"{v:.5g}")
    page = f"""<!doctype html><html lang="en"><head><meta charset="utf-8">
<title>San Francisco SIR forecast {results.future.reference_date}</title>
<style>body{{font-family:sans-serif;margin:2em}} .stale{{background:#fde2e2;padding:1em}}
table{{border-collapse:collapse}} td,th{{border:1px solid #ccc;padding:3px 6px}}</style></head>
<body><h1>San Francisco SIR forecast — reference date {results.future.reference_date}</h1>
{banner}<p>{html.escape(results.vintage)}</p>
<p>Model {results.models.key[:12]} ({html.escape(results.models.encoder)} encoder,
{"reused from cache" if results.models.reused else "trained in this run"}).</p>
<h2>Latest estimates</h2>{latest}<h2>NLL</h2>{nll}<h2>β, γ (latest days)</h2>{params}
</body></html>
"""
    atomic_write_text(out_dir / "report.html", page)
    return "report.html"
