"""The weekly San Francisco forecast as plain library steps (the Prefect flow only wraps them).

Steps, each a function here so it can be called, tested and timed without Prefect:

1. :func:`load_series` — DataSF cases/deaths/tests (live with cache fallback, cache only, or
   imported CSV exports), trimmed of the last days still under revision;
   :func:`series_to_sir` — S, I, R proportions (``pipeline.data.sir_transform``).
2. :func:`simulate_training_data` — the synthetic ``sir-sf`` ensemble (the SIR prior fitted to
   the SF series, :mod:`pipeline.systems.sir`; the paper's ``sir-multi`` prior sits far from SF,
   docs/systems.md) cut into forward and backward windows whose target is the joint
   (S, I, R, β, γ) — the paper's "joint state and parameter estimation".
3. :func:`train_or_reuse_models` — train the forward and backward estimators, or reuse the cached
   pair (:mod:`pipeline.training.model_store`, key = training config + training-data hash).
4. :func:`latest_estimates` — forward estimate of the day after the last observation and backward
   estimate of the day before the last window (both from the latest R observations).
5. :func:`rollouts` — rolling rollouts re-anchored every 7 and 28 days, forward and backward
   (``pipeline.inference.rollout``), plus :func:`future_paths`: forward sample paths past the last observed
   day (the paper's rollout forecast; the published forecast is step 9's).
6. :func:`parameter_track` — β, γ over time (posterior mean and 95 % interval per day).
7. :func:`nll_table` — the paper's Table 5: mean NLL of the observed state under the flow's state
   marginal at random days along the SF trajectory (forward / backward).
8. :func:`seeded_smc` — the paper's hybrid: particles drawn from the forward joint estimate seed a
   bootstrap filter over the following observations; 3σ bands.
9. :func:`weekly_forecast` — the published forecast of weekly cases and I (an ensemble of a
   flow member and AutoETS, :mod:`pipeline.ensemble`) at the latest Saturday, with the same
   method's real-time backtest over every earlier Saturday.

Models come from :mod:`pipeline.training.presets` (``sir-sf-joint`` × encoder × recipe, one preset per
direction) and are trained and saved with :func:`pipeline.training.trainer.train_and_save`.

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

from pipeline.errors import CheckpointError, ConfigError, OfflineError
from pipeline.ensemble.nf_member import GrowthModelConfig
from pipeline.outputs.hubverse import Submission
from pipeline.ensemble.weekly import WeeklyConfig, WeeklyForecast
from pipeline.progress import ProgressReporter
from pipeline.evaluation.scoring import CENTRAL_LEVELS
from pipeline.systems.waves import WavePrior

log = logging.getLogger(__name__)

DataSourceKind = Literal["live", "cache", "import"]
STATE_NAMES = ("S", "I", "R")
JOINT_NAMES = ("S", "I", "R", "beta", "gamma")
DIRECTIONS = ("forward", "backward")
# Encoder choice -> the paper's Table 5 column name.
VARIANT_LABELS = {"transformer": "Transformer", "transformer-ke": "Transformer + KE",
                  "mamba": "Mamba-SSM", "mlp": "MLP"}
# The report's one interval convention: 50 % and 90 % central intervals (plus the median).
REPORT_LEVELS = CENTRAL_LEVELS
PARAMETER_LEVELS = (0.025, *REPORT_LEVELS, 0.975)
# Per-step seed offsets: changing one step's draws never shifts another's.
_SEED_OFFSETS = {"simulate": 0, "train_forward": 11, "train_backward": 12, "latest": 21,
                 "rollout": 31, "future": 41, "params": 51, "nll": 61, "smc": 71,
                 "weekly": 91, "train_growth": 92}


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
    base_url: str | None = None    # a DataSF mirror/proxy; None: $FLOWCAST_DATASF_BASE_URL or DataSF
    fetch_deadline_s: float = 300.0  # per dataset, every page and retry (wall clock)

    @property
    def task_timeout_s(self) -> float:
        """The fetch task's time limit: three datasets' deadlines plus a minute of slack."""
        return 3 * self.fetch_deadline_s + 60.0

    def __post_init__(self) -> None:
        if self.kind not in ("live", "cache", "import"):
            raise ConfigError(f"data source must be live, cache or import, got {self.kind!r}")
        if self.kind == "import" and not self.import_paths:
            raise ConfigError("data source 'import' needs import_paths (DataSF CSV exports)")


@dataclass(frozen=True)
class ForecastConfig:
    """Everything that determines one weekly run (with the data and the seed).

    The models come from one named training preset (:func:`pipeline.training.presets.get_preset`:
    ``training_preset`` × ``encoder`` × ``recipe``, one per direction) — the single source of the
    dataset, estimator and optimiser settings. ``n_trajectories``, ``horizon_days``,
    ``train_iterations``, ``train_batch_size`` and ``eval_every`` only shrink it (None = the
    preset's), so the ``tiny`` preset is the same model family at toy size.
    """

    preset: str = "default"
    training_preset: str = "sir-sf-joint"  # the paper's sir-joint prior does not cover SF
    recipe: str = "fast"
    encoder: str = "transformer"          # the paper's SF runs use the transformer
    n_trajectories: int | None = None     # synthetic ensemble size (None: the prior's)
    horizon_days: int | None = None       # None: the prior's
    train_iterations: int | None = None   # None: the recipe's
    train_batch_size: int | None = None   # None: the recipe's
    eval_every: int | None = None         # None: the recipe's
    rollout_windows: tuple[int, ...] = (7, 28)
    # Rolling rollouts cover the whole history (~740 days x 4 views): sampling the MAF inverse
    # for anchors x paths rows dominates a cached run, so 64 paths (enough for 2-sigma bands)
    # keep the weekly run near a minute; the 4-week hub forecast still uses hub_paths.
    rollout_paths: int = 64
    forecast_days: int = 28               # future paths: 4 weeks for the hub CSV
    hub_paths: int = 200
    n_samples: int = 500                  # draws per estimate
    parameter_stride_days: int = 2
    nll_locations: int = 100
    smc_particles: int = 1000
    smc_days: int = 56                    # observations the seeded filter runs over
    # SIR process noise of the NF-seeded filter, per sqrt(day): a fifth of the prior's
    # observation noise, so the filter follows SF's I (median 8e-4) instead of diffusing it; the
    # paper's 1e-3 was sized for sir-multi's I of ~0.1. (The backtest's plain SMC keeps its own.)
    smc_process_sigma: float = 1e-4
    trailing_days: int = 14
    seed: int = 0
    data: DataSourceConfig = field(default_factory=DataSourceConfig)
    # The published forecast: an ensemble of the flow member (its own model) and AutoETS, with
    # its real-time backtest over every Saturday origin (pipeline.ensemble.weekly).
    weekly: WeeklyConfig = field(default_factory=WeeklyConfig)

    def __post_init__(self) -> None:
        if any(w < 1 for w in self.rollout_windows):
            raise ConfigError(f"rollout_windows={self.rollout_windows} must all be >= 1")
        for name in ("rollout_paths", "forecast_days", "hub_paths", "n_samples",
                     "parameter_stride_days", "nll_locations", "smc_particles", "smc_days"):
            if getattr(self, name) < 1:
                raise ConfigError(f"ForecastConfig.{name}={getattr(self, name)} must be >= 1")
        for name in ("n_trajectories", "horizon_days", "train_iterations", "train_batch_size",
                     "eval_every"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ConfigError(f"ForecastConfig.{name}={value} must be >= 1 (or None)")
        if self.smc_process_sigma < 0:
            raise ConfigError(f"ForecastConfig.smc_process_sigma={self.smc_process_sigma} < 0")
        self.training_preset_for("forward")  # unknown preset/encoder/recipe fail here, early

    def step_seed(self, step: str) -> int:
        return self.seed * 1000 + _SEED_OFFSETS[step]

    def weekly_config(self) -> WeeklyConfig:
        """``weekly`` with the run's seeds (the flow member's training seed included)."""
        growth = dataclasses.replace(self.weekly.growth, seed=self.step_seed("train_growth"))
        return dataclasses.replace(self.weekly, growth=growth, seed=self.step_seed("weekly"))

    def training_preset_for(self, direction: str) -> Any:
        """The :class:`~pipeline.training.presets.TrainingPreset` of the ``direction`` model."""
        from pipeline.training.presets import get_preset

        preset = get_preset(self.training_preset, self.encoder, recipe=self.recipe,
                            direction=direction, seed=self.step_seed(f"train_{direction}"),
                            dataset_seed=self.step_seed("simulate"),
                            n_trajectories=self.n_trajectories)
        preset = preset.with_overrides(iterations=self.train_iterations,
                                       batch_size=self.train_batch_size)
        if self.eval_every is not None:
            preset = dataclasses.replace(preset, train=dataclasses.replace(
                preset.train, eval_every=self.eval_every))
        return preset

    @property
    def window(self) -> int:
        """R, the context length of the preset (the paper's five observations)."""
        return int(self.training_preset_for("forward").dataset.window)

    @property
    def prior(self) -> Any:
        """The :class:`~pipeline.systems.sir.SIRPrior` the models train on (``horizon_days``
        applied); its noise and parameter ranges are also the particle filters'."""
        prior = self.training_preset_for("forward").dataset.system_config()
        if self.horizon_days is not None:
            prior = dataclasses.replace(prior, horizon_days=self.horizon_days)
        return prior

    def training_identity(self) -> dict[str, Any]:
        """What determines the trained models (the model-cache key is built from this)."""
        return {"presets": {d: self.training_preset_for(d).to_dict() for d in DIRECTIONS},
                "horizon_days": self.horizon_days}


FORECAST_PRESETS: dict[str, ForecastConfig] = {
    # The product: sir-sf-joint × transformer × fast recipe on the full sir-sf ensemble (2,000
    # trajectories × 150 days). The recipe's 6,000 iterations per direction (~75–90 ms per
    # batch-512 transformer step on one core) would take ~18 min for the pair; 2,500 with the
    # same cosine schedule fit the 15-minute from-scratch budget (docs/orchestration.md).
    "default": ForecastConfig(preset="default", train_iterations=2_500),
    # Seconds, for tests and smoke runs: same preset family with the MLP encoder, a small
    # ensemble, a short horizon, few iterations, samples, particles and backtest origins.
    "tiny": ForecastConfig(preset="tiny", encoder="mlp", n_trajectories=16, horizon_days=160,
                           train_iterations=30, train_batch_size=256, eval_every=10,
                           rollout_paths=16, hub_paths=200, n_samples=128,
                           parameter_stride_days=7, nll_locations=20, smc_particles=200,
                           smc_days=28,
                           weekly=WeeklyConfig(
                               growth=GrowthModelConfig(n_trajectories=120, iterations=30,
                                                        batch_size=256,
                                                        prior=WavePrior(days=140)),
                               n_paths=100),
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
    client = ClientConfig(max_retries=source.http_retries, backoff_base_s=source.http_backoff_s,
                          fetch_deadline_s=source.fetch_deadline_s,
                          **({"base_url": source.base_url} if source.base_url else {}))
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
    times = ((dates - dates[0]) / pd.Timedelta(days=1)).to_numpy(dtype=np.float64, copy=True)
    values = sir_frame[list(STATE_NAMES)].to_numpy(dtype=np.float64, copy=True)  # writable
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
    """One synthetic ensemble (the preset's dataset, ``horizon_days`` override applied) cut into
    the forward and backward windows of the two presets, each split into train/validation."""
    from pipeline.training.datasets import dataset_sha256, train_validation_split, windows_from_sir
    from pipeline.io import sha256_bytes
    from pipeline.systems.sir import simulate_ensemble

    dataset = config.training_preset_for("forward").dataset
    prior = config.prior
    ensemble = simulate_ensemble(prior, prior.n_trajectories, seed=dataset.seed,
                                 progress=progress)
    splits, hashes = {}, []
    for direction in DIRECTIONS:
        ds_config = config.training_preset_for(direction).dataset
        ds = windows_from_sir(ensemble, direction=direction, target=ds_config.target,
                              window=ds_config.window, val_fraction=ds_config.val_fraction)
        hashes.append(dataset_sha256(ds))
        # Standardization in the coordinates the model's flow works in (its target transform).
        splits[direction] = train_validation_split(
            ds, config.training_preset_for(direction).estimator.target_transform)
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
    from pipeline.training.model_store import ModelStore

    store = ModelStore(store_root or model_store_root())

    def build(out_dir: Path) -> dict[str, Any]:
        best = {}
        for direction in DIRECTIONS:
            best[direction] = _train_direction(config, data, direction, out_dir / direction,
                                               progress)
        return {"best_val_nll": best}

    entry = store.get_or_build(config.training_identity(), data.data_sha256, build,
                               retrain=retrain)
    return _load_models(config, entry)


def _load_models(config: ForecastConfig, entry: Any) -> TrainedModels:
    """The forward/backward pair of a model-store entry, checked against the presets' configs."""
    from pipeline.training.checkpoints import load_checkpoint

    loaded = {d: load_checkpoint(entry.path / d / "model.pt",
                                 expected_config=config.training_preset_for(d).estimator)
              for d in DIRECTIONS}
    for direction, model in loaded.items():
        # Both directions share one architecture, so the config check cannot tell a swapped pair
        # apart; the direction recorded at training time can (issue 15).
        recorded = model.meta.extra.get("direction")
        if recorded is not None and recorded != direction:
            raise CheckpointError(f"{entry.path / direction / 'model.pt'} is a {recorded} model "
                                  f"(checkpoint metadata direction) in the {direction} slot: "
                                  f"forward and backward checkpoints swapped; retrain (--retrain)")
        model.estimator.eval()
    return TrainedModels(
        forward=loaded["forward"].estimator, backward=loaded["backward"].estimator,
        key=entry.key, reused=entry.reused, path=entry.path,
        histories={d: list(loaded[d].meta.history) for d in DIRECTIONS},
        best_val_nll={d: float(loaded[d].meta.extra.get("best_val_nll_original", float("nan")))
                      for d in DIRECTIONS},
        encoder=config.encoder)


def cached_variant_models(config: ForecastConfig, data: TrainingData, *,
                          store_root: Path | None = None) -> dict[str, TrainedModels]:
    """The other encoder variants (paper Table 5 columns) already in the model store for the
    same preset, recipe and training data — e.g. trained by ``flows.scale_out``. Never trains."""
    from pipeline.training.model_store import ModelStore, model_key
    from pipeline.training.presets import ENCODER_CHOICES

    store = ModelStore(store_root or model_store_root())
    out = {}
    for encoder in ENCODER_CHOICES:
        if encoder == config.encoder:
            continue
        variant = dataclasses.replace(config, encoder=encoder)
        entry = store.get(model_key(variant.training_identity(), data.data_sha256))
        if entry is not None:
            out[encoder] = _load_models(variant, entry)
    return out


def _train_direction(config: ForecastConfig, data: TrainingData, direction: str, out_dir: Path,
                     progress: ProgressReporter | None) -> float:
    """Train the ``direction`` preset and write it with ``training.train_and_save``."""
    from pipeline.models.estimator import build_estimator
    from pipeline.training.trainer import train_and_save

    preset = config.training_preset_for(direction)
    train_ds, val_ds = data.splits[direction]
    estimator = build_estimator(preset.estimator, train_ds.stats, seed=preset.train.seed)
    result = train_and_save(estimator, train_ds, val_ds, preset.train, preset.kinetic, out_dir,
                            estimator_config=preset.estimator, progress=progress,
                            preset=preset,
                            extra={"direction": direction, "forecast_preset": config.preset,
                                   "training_preset": preset.run_name})
    log.info("trained %s model: best validation NLL %.3f at iteration %d (%s)", direction,
             result.best_val_nll_original, result.best_iteration, result.stop_reason)
    return float(result.best_val_nll_original)


# ------------------------------------------------------------------------------ estimates


def _window(times: np.ndarray, values: np.ndarray, rows: slice, target_time: float) -> Any:
    from pipeline.inference.estimate import ObservationWindow

    return ObservationWindow(times=times[rows], values=values[rows], target_time=float(target_time))


@dataclass(frozen=True)
class LatestEstimates:
    """Summaries of the latest forward (next day) and backward (day before the window) estimates."""

    table: pd.DataFrame  # direction, date, component, mean, std, q0.025, q0.5, q0.975
    samples: dict[str, Tensor]  # direction -> (n, len(names)) joint draws (the report's R_t)
    dates: dict[str, str]
    names: tuple[str, ...] = JOINT_NAMES


def latest_estimates(models: TrainedModels, sir_frame: pd.DataFrame,
                     config: ForecastConfig) -> LatestEstimates:
    from pipeline.inference.estimate import estimate

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
    from pipeline.inference.rollout import RolloutConfig, rolling_rollout

    times, values, _ = sir_arrays(sir_frame)
    out = {}
    for direction in DIRECTIONS:
        for every in config.rollout_windows:
            rc = RolloutConfig(n_paths=config.rollout_paths,
                               feedback_noise_sigma=config.prior.obs_sigma,
                               seed=config.step_seed("rollout") + every)
            out[(direction, every)] = rolling_rollout(
                models.by_direction(direction), times, values, every, direction, rc,
                names=JOINT_NAMES, window_length=config.window, progress=progress)
    return out


@dataclass(frozen=True)
class FuturePaths:
    dates: pd.DatetimeIndex
    samples: Tensor          # (P, H, 5): S, I, R, beta, gamma
    reference_date: dt.date


def future_paths(models: TrainedModels, sir_frame: pd.DataFrame,
                 config: ForecastConfig) -> FuturePaths:
    """Forward sample paths for ``forecast_days`` days after the last observed day."""
    from pipeline.inference.rollout import RolloutConfig, rollout

    times, values, dates = sir_arrays(sir_frame)
    r = config.window
    window = _window(times, values, slice(len(times) - r, len(times)), times[-1] + 1.0)
    rc = RolloutConfig(n_paths=config.hub_paths, feedback_noise_sigma=config.prior.obs_sigma,
                       seed=config.step_seed("future"))
    result = rollout(models.forward, window, config.forecast_days, 1.0, "forward", rc,
                     names=JOINT_NAMES, window_length=r)
    future_dates = pd.date_range(dates[-1] + pd.Timedelta(days=1), periods=config.forecast_days,
                                 freq="D")
    return FuturePaths(future_dates, result.samples, dates[-1].date())


def parameter_track(models: TrainedModels, sir_frame: pd.DataFrame,
                    config: ForecastConfig) -> pd.DataFrame:
    """β, γ (and the state) per day from the R observations before (fw) / after (bw) the day.

    Long table: direction, date, component, mean, std, q0.025, q0.05, q0.25, q0.5, q0.75,
    q0.95, q0.975; one flow call per direction for all days at once. Component ``Rt`` is the
    effective reproduction number β·S/γ computed per joint sample (its posterior, not a ratio of
    medians); the report's intervals are the 50 % and 90 % ones.
    """
    from pipeline.inference.estimate import batch_window_context, sample_conditional

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
        rt = samples[:, :, 3] * samples[:, :, 0] / samples[:, :, 4]                 # β S / γ
        samples = torch.cat([samples, rt[..., None]], dim=-1)
        q = torch.quantile(samples, torch.tensor(PARAMETER_LEVELS, dtype=torch.float64), dim=1)
        for d, name in enumerate((*JOINT_NAMES, "Rt")):
            frames.append(pd.DataFrame({
                "direction": direction, "date": dates[targets].strftime("%Y-%m-%d"),
                "component": name, "mean": samples[:, :, d].mean(1).numpy(),
                "std": samples[:, :, d].std(1).numpy(),
                **{f"q{level:g}": q[k, :, d].numpy()
                   for k, level in enumerate(PARAMETER_LEVELS)}}))
    return pd.concat(frames, ignore_index=True)


def nll_table(models: TrainedModels, sir_frame: pd.DataFrame,
              config: ForecastConfig) -> pd.DataFrame:
    """Mean NLL of the observed (S, I, R) at ``nll_locations`` random days, fw and bw.

    The joint flow models (S, I, R, β, γ); the true β, γ of SF are unknown, so we score the
    *state marginal*: a Gaussian KDE (``metrics.kde_log_prob``) of the flow's (S, I, R) draws,
    evaluated at the observed state — the paper's "NLL of the estimated conditional density given
    the true state", aggregated across compartments (one joint 3-D density).
    """
    from pipeline.inference.estimate import batch_window_context, sample_conditional
    from pipeline.evaluation.metrics import kde_log_prob, mean_nll

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
        rows.append({"direction": direction,
                     "variant": VARIANT_LABELS.get(models.encoder, models.encoder),
                     "locations": len(targets), "mean_nll": mean_nll(log_p.numpy())})
    return pd.DataFrame(rows)


def nll_table_variants(models: TrainedModels, variants: dict[str, TrainedModels],
                       sir_frame: pd.DataFrame, config: ForecastConfig) -> pd.DataFrame:
    """:func:`nll_table` of the run's models and of every cached variant, same days and seed."""
    frames = [nll_table(m, sir_frame, config) for m in (models, *variants.values())]
    return pd.concat(frames, ignore_index=True)


def seeded_smc(models: TrainedModels, sir_frame: pd.DataFrame, config: ForecastConfig) -> Any:
    """NF-seeded SMC over the last ``smc_days`` days: flow draws at the first day seed it."""
    from pipeline.inference.estimate import sample_conditional, window_context
    from pipeline.inference.smc import DEFAULT_QUANTILES, SMCConfig, seeded_filter
    from pipeline.inference.smc_models import SIRParamsModel

    times, values, dates = sir_arrays(sir_frame)
    r = config.window
    start = max(r, len(times) - config.smc_days)
    window = _window(times, values, slice(start - r, start), times[start])
    context, mask = window_context(window, "forward", r)
    particles = sample_conditional(models.forward, context, mask, config.smc_particles,
                                   config.step_seed("smc")).double()                # (1, N, 5)
    _check_valid_seed(particles)
    prior = config.prior
    # The filter's model is the training prior's: its noise, and beta (and gamma) drifting as
    # fast as the prior's walk. Static parameters (jitter 0) cannot follow a wave's turn: on the
    # last 56 SF days the particles then collapsed (median ESS 1 of 1,000, 9 % of I inside the
    # 3-sigma band) against median ESS 437 and 88 % with the walk's jitter.
    model = SIRParamsModel.create(prior_mean=values[start], prior_std=prior.obs_sigma,
                                  beta_range=prior.beta, gamma_range=prior.gamma,
                                  obs_sigma=prior.obs_sigma,
                                  process_sigma=config.smc_process_sigma,
                                  param_jitter=prior.beta_walk_sigma)
    observations = torch.as_tensor(values[start:])[None]
    result = seeded_filter(particles, observations, model,
                           SMCConfig(num_particles=config.smc_particles,
                                     seed=config.step_seed("smc"),
                                     # the report's 50 %/90 % bands need these levels recorded
                                     quantiles=tuple(sorted({*DEFAULT_QUANTILES,
                                                             *REPORT_LEVELS}))),
                           times=torch.as_tensor(times[start:]))
    return SMCRun(result=result, dates=dates[start:])


def _check_valid_seed(particles: Tensor) -> None:
    """The seeding draws must already be states and rates: the joint model's log-ratio
    coordinates guarantee it, so a violation means a wrong model, not something to clip."""
    state, rates = particles[..., :3], particles[..., 3:]
    bad = ((state < 0).any(-1) | ((state.sum(-1) - 1).abs() > 1e-6)
           | (rates <= 0).any(-1) | ~torch.isfinite(particles).all(-1))
    if bool(bad.any()):
        raise ConfigError(f"{int(bad.sum())} of {bad.numel()} flow draws seeding the SMC filter "
                          "are not valid S/I/R states with positive rates; the forecast's joint "
                          "model must use target_transform='sir-log-ratio' (retrain it)")


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


def weekly_forecast(series: Any, sir: Any, config: ForecastConfig,
                    progress: ProgressReporter | None = None) -> WeeklyForecast:
    """The published forecast (ensemble of the flow member and AutoETS, recalibrated) at the
    latest Saturday, and the same method's real-time forecasts at every earlier Saturday
    (:mod:`pipeline.ensemble.weekly`). The flow member comes from the model store."""
    from pipeline.ensemble.backtest import sf_history
    from pipeline.ensemble.weekly import forecast_weekly

    return forecast_weekly(sf_history(series, sir), config.weekly_config(), model_store_root(),
                           progress)


def published_skill(weekly: WeeklyForecast) -> dict[str, dict[str, float | None]]:
    """Relative WIS vs the hub baseline (h1–h4, all) of the published forecast, per target."""
    summary = weekly.summary()["by_target"]
    return {target: dict(summary[target]["published"]["relative_wis_vs_baseline"])
            for target in summary}


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
    weekly: WeeklyForecast | None = None   # the published forecast and its real-time backtest


def write_tables(results: ForecastResults, out_dir: Path) -> list[str]:
    """CSV tables + hub CSV + results.json into ``out_dir``; returns the file names written."""
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
    if results.weekly is not None:
        tables.update(weekly_tables(results.weekly))
    for name, frame in tables.items():
        atomic_write_text(out_dir / name, frame.to_csv(index=False))
    written = list(tables) + ["results.json"]
    if results.weekly is not None:
        atomic_write_json(out_dir / "backtest_summary.json", results.weekly.summary())
        submission = write_submission(results.weekly, out_dir, submission_run_date(results))
        written += ["backtest_summary.json", submission.path.relative_to(out_dir).as_posix()]
    summary = results_summary(results)
    atomic_write_json(out_dir / "results.json", summary)
    return sorted(written)


def weekly_tables(weekly: WeeklyForecast) -> dict[str, pd.DataFrame]:
    """The published forecast in hub format (quantiles and sample paths of I and weekly cases),
    every forecaster's quantiles beside it, and the real-time backtest's scores."""
    from pipeline.ensemble.backtest import PUBLISHED, hub_frame

    population = weekly.history.population
    frames = [hub_frame(f, population).assign(forecaster=name)
              for name, f in weekly.member_forecasts().items() if name != PUBLISHED]
    members = pd.concat(frames, ignore_index=True)
    scores = weekly.backtest.scores.assign(
        origin_date=lambda f: pd.to_datetime(f["origin_date"]).dt.strftime("%Y-%m-%d"),
        target_end_date=lambda f: pd.to_datetime(f["target_end_date"]).dt.strftime("%Y-%m-%d"))
    return {"hub_forecast.csv": hub_frame(weekly.latest, population),
            "member_forecasts.csv": members,
            "backtest_scores.csv": scores}


def write_submission(weekly: WeeklyForecast, hub_dir: Path, run_date: dt.date) -> Submission:
    """The hubverse model-output CSV of the published forecast under ``hub_dir/model-output/``,
    validated against the repository's ``hub-config/tasks.json`` when it is there."""
    from pipeline.outputs.hubverse import SubmissionConfig, write_model_output

    return write_model_output(weekly.latest, population=weekly.history.population,
                              run_date=run_date, hub_dir=hub_dir, tasks=_hub_tasks(),
                              config=SubmissionConfig(n_samples=min(200, _n_paths(weekly))))


def submission_run_date(results: ForecastResults) -> dt.date:
    """The run's date for the hub round: the data's cut-off, the last kept day plus the
    ``trailing_days`` dropped as still under revision (today, for a live run on fresh data), so a
    re-run on the same data lands in the same round."""
    last = pd.Timestamp(results.sir_frame["date"].iloc[-1]).date()
    return last + dt.timedelta(days=results.config.trailing_days)


def _n_paths(weekly: WeeklyForecast) -> int:
    paths = weekly.latest.paths
    return 0 if paths is None else int(paths.shape[0])


def _hub_tasks() -> dict[str, Any] | None:
    from pipeline.outputs.hubverse import load_tasks_config

    tasks = Path(__file__).resolve().parents[2] / "hub-config" / "tasks.json"
    return load_tasks_config(tasks) if tasks.is_file() else None

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
            "backtest": published_skill(results.weekly) if results.weekly is not None else None,
            "headline": headline_record(results) if results.weekly is not None else None,
            "config": dataclasses.asdict(results.config)}


def headline_record(results: ForecastResults) -> dict[str, Any]:
    """The report's page-1 headline as JSON (``results.json``, the run index)."""
    from pipeline.report.headline import compute_headline

    return compute_headline(results).to_dict()


def write_report(results: ForecastResults, out_dir: Path) -> list[str]:
    """report.html + report.pdf (``pipeline.report.weekly``); returns the file names written."""
    from pipeline.report import build_forecast_report

    return list(build_forecast_report(results, out_dir))
