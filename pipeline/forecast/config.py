"""What determines one weekly run: :class:`ForecastConfig`, the named presets, and their resolution.

:class:`ForecastConfig` nests one frozen dataclass per concern: where the data come from
(:class:`DataSourceConfig`, here), the settings of each step (training, estimates, rollouts, SMC,
the nowcast, outputs: :mod:`pipeline.forecast.settings`) and the published forecast. The training
presets and the SIR prior they imply are resolved once per config
(:attr:`ForecastConfig.resolved`), not at every use.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

from pipeline.data.california.counties import SAN_FRANCISCO, california_county
from pipeline.data.core.cache import data_dir
from pipeline.training.model_store import MODELS_FOLDER
from pipeline.backtest.track_record import TrackRecordConfig
from pipeline.members.nf.growth import GrowthModelConfig
from pipeline.members.nf.real import FineTuneConfig
from pipeline.members.boosting import BoostingConfig, deep_trees
from pipeline.members.published import MembersConfig
from pipeline.errors import ConfigError
from pipeline.forecast.settings import (EstimateSettings, NowcastSettings, OutputSettings,
                                        RolloutSettings, SMCSettings, TrainingSettings)
from pipeline.names import DIRECTIONS, Direction
from pipeline.systems.waves import WavePrior, recovery_rate
from pipeline.training.presets import TrainingPreset, get_preset

DataSourceKind = Literal["live", "cache", "import"]
SeedStep = Literal["simulate", "train_forward", "train_backward", "latest", "rollout", "future",
                   "params", "nll", "smc", "weekly", "train_growth", "nowcast"]
# Per-step seed offsets: changing one step's draws never shifts another's.
_SEED_OFFSETS: dict[SeedStep, int] = {
    "simulate": 0, "train_forward": 11, "train_backward": 12, "latest": 21, "rollout": 31,
    "future": 41, "params": 51, "nll": 61, "smc": 71, "weekly": 91, "train_growth": 92,
    "nowcast": 93}


@dataclass(frozen=True)
class DataSourceConfig:
    """Where the forecast's series comes from: San Francisco from DataSF (``county`` None, the
    default), or the California ``county`` (as CDPH spells it) from CDPH's county file.

    ``live``: fetch DataSF, or the CDPH file from the CHHS portal (HTTP retries with backoff
    inside the client), falling back to the cache with a staleness note; ``cache``: offline,
    cache only; ``import``: import the given DataSF CSV exports (CDPH ``covid19cases_test.csv``
    downloads for a county) into the cache (``flowcast data import``), then read it offline.
    """

    kind: DataSourceKind = "live"
    import_paths: tuple[str, ...] = ()
    http_retries: int = 3          # per HTTP request, exponential backoff inside the client
    http_backoff_s: float = 2.0
    task_retries: int = 2          # whole-fetch retries by the orchestrator (live only)
    task_retry_delay_s: float = 10.0
    base_url: str | None = None    # a DataSF mirror/proxy; None: $FLOWCAST_DATASF_BASE_URL or DataSF
    fetch_deadline_s: float = 300.0  # per dataset, every page and retry (wall clock)
    # days dropped from the end of every dataset; 0: the run keeps every day and nowcasts the
    # ones still being reported (NowcastSettings); without a nowcast it falls back to 14
    trailing_days: int = 0
    county: str | None = None      # a California county from CDPH; None: San Francisco, DataSF
    # the flowcast data folder (cache, model store, memo, delay models), set where the run's
    # config is built (the flow, the CLI); None: $FLOWCAST_DATA_DIR or ./data, read at use
    data_dir: str | None = None

    @property
    def folder(self) -> Path:
        """The data folder the run reads and writes (:attr:`data_dir`)."""
        return data_dir(self.data_dir)

    @property
    def place(self) -> str:
        """The place forecast: the county, or San Francisco."""
        return self.county or SAN_FRANCISCO

    @property
    def provider(self) -> str:
        """Who publishes the series: DataSF (San Francisco) or CDPH (a county)."""
        return "DataSF" if self.county is None else "CDPH"

    @property
    def task_timeout_s(self) -> float:
        """The fetch task's time limit: three datasets' deadlines plus a minute of slack."""
        return 3 * self.fetch_deadline_s + 60.0

    def __post_init__(self) -> None:
        if self.kind not in ("live", "cache", "import"):
            raise ConfigError(f"data source must be live, cache or import, got {self.kind!r}")
        if self.kind == "import" and not self.import_paths:
            raise ConfigError("data source 'import' needs import_paths (DataSF CSV exports, or "
                              "CDPH files for a county)")
        if self.trailing_days < 0:
            raise ConfigError(f"DataSourceConfig.trailing_days={self.trailing_days} must be >= 0")
        if self.county is not None and california_county(self.county) != self.county:
            raise ConfigError(f"county {self.county!r} is spelled "
                              f"{california_county(self.county)!r} in the CDPH data")


@dataclass(frozen=True)
class ResolvedTraining:
    """The training presets of both directions and the multi-wave prior they train on (the
    flow member's)."""

    presets: dict[Direction, TrainingPreset]
    prior: WavePrior

    @property
    def window(self) -> int:
        """R, the context length in days."""
        return int(self.presets["forward"].dataset.window)

    @property
    def gamma(self) -> float:
        """γ = 1/L per day, fixed by the S/I/R conversion's infectious window (not estimated)."""
        return recovery_rate(self.prior)


@dataclass(frozen=True)
class ForecastConfig:
    """Everything that determines one weekly run (with the data and the seed)."""

    preset: str = "default"
    seed: int = 0
    data: DataSourceConfig = field(default_factory=DataSourceConfig)
    training: TrainingSettings = field(default_factory=TrainingSettings)
    estimates: EstimateSettings = field(default_factory=EstimateSettings)
    rollouts: RolloutSettings = field(default_factory=RolloutSettings)
    smc: SMCSettings = field(default_factory=SMCSettings)
    # The published forecast: the members' equal-weight log average, with its real-time track
    # record over every Saturday origin (pipeline.backtest.track_record).
    track_record: TrackRecordConfig = field(default_factory=TrackRecordConfig)
    nowcast: NowcastSettings = field(default_factory=NowcastSettings)
    outputs: OutputSettings = field(default_factory=OutputSettings)

    @property
    def store_root(self) -> Path:
        """The model store in the run's data folder (:attr:`DataSourceConfig.folder`)."""
        return self.data.folder / MODELS_FOLDER

    def __post_init__(self) -> None:
        _ = self.resolved  # an unknown preset, encoder or recipe fails here, early

    def step_seed(self, step: SeedStep) -> int:
        return self.seed * 1000 + _SEED_OFFSETS[step]

    @cached_property
    def resolved(self) -> ResolvedTraining:
        presets: dict[Direction, TrainingPreset] = {d: self._training_preset(d) for d in DIRECTIONS}
        if presets["forward"].dataset.system != "waves":
            raise ConfigError(f"training preset {self.training.preset!r} does not train on the "
                              "multi-wave prior (sf-waves); the SF forecast's joint models "
                              "share that prior with its flow member")
        return ResolvedTraining(presets=presets, prior=self.track_record.members.growth.prior)

    def _training_preset(self, direction: Direction) -> TrainingPreset:
        settings = self.training
        seed_step: SeedStep = "train_forward" if direction == "forward" else "train_backward"
        preset = get_preset(settings.preset, settings.encoder, recipe=settings.recipe,
                            direction=direction, seed=self.step_seed(seed_step),
                            dataset_seed=self.step_seed("simulate"),
                            n_trajectories=settings.n_trajectories)
        preset = preset.with_overrides(iterations=settings.iterations,
                                       batch_size=settings.batch_size)
        if settings.eval_every is not None:
            preset = dataclasses.replace(preset, train=dataclasses.replace(
                preset.train, eval_every=settings.eval_every))
        return preset

    def track_record_config(self) -> TrackRecordConfig:
        """``track_record`` with the run's seeds (the flow member's training seed included)."""
        members = self.track_record.members
        growth = dataclasses.replace(members.growth, seed=self.step_seed("train_growth"))
        return dataclasses.replace(self.track_record,
                                   members=dataclasses.replace(members, growth=growth),
                                   seed=self.step_seed("weekly"))

    def training_identity(self) -> dict[str, object]:
        """What determines the trained joint models (the model-store key is built from this)."""
        presets = self.resolved.presets
        return {"presets": {d: presets[d].to_dict() for d in DIRECTIONS},
                "prior": dataclasses.asdict(self.resolved.prior)}

    def as_dict(self) -> dict[str, object]:
        return dataclasses.asdict(self)


FORECAST_PRESETS: dict[str, ForecastConfig] = {
    # The product: sf-waves-joint × MLP × fast recipe on 2,000 trajectories of the flow
    # member's multi-wave prior (docs/forecasting.md "One model of the epidemic").
    "default": ForecastConfig(preset="default"),
    # Seconds, for tests and smoke runs: same preset family with a small ensemble, a short
    # prior, few iterations, samples, particles and backtest origins (the latest 30).
    "tiny": ForecastConfig(
        preset="tiny",
        training=TrainingSettings(n_trajectories=16, iterations=30, batch_size=256,
                                  eval_every=10, background_members=False),
        estimates=EstimateSettings(n_samples=128, parameter_stride_days=7, nll_locations=20),
        rollouts=RolloutSettings(paths=16, future_paths=200),
        smc=SMCSettings(particles=200, days=28, member_particles=100),
        track_record=TrackRecordConfig(
            members=MembersConfig(growth=GrowthModelConfig(n_trajectories=120, iterations=30,
                                                           batch_size=256,
                                                           prior=WavePrior(days=140)),
                                  finetune=FineTuneConfig(iterations=10, refit_every_weeks=26),
                                  boosting=deep_trees(BoostingConfig(n_estimators=10))),
            n_paths=100, recent_origins=30),
        nowcast=NowcastSettings(completions=8, nowcast_samples=100),
        data=DataSourceConfig(http_retries=2, http_backoff_s=0.0, task_retries=1,
                              task_retry_delay_s=0.0)),
}


def resolve_config(preset: str, *, encoder: str | None = None, seed: int | None = None,
                   data: DataSourceConfig | None = None,
                   output_dir: str | None = None) -> ForecastConfig:
    """The named preset with the run-time choices a user makes (None keeps the preset's)."""
    try:
        config = FORECAST_PRESETS[preset]
    except KeyError:
        raise ConfigError(f"unknown forecast preset {preset!r}; known: "
                          f"{sorted(FORECAST_PRESETS)}") from None
    if encoder is not None:
        config = dataclasses.replace(
            config, training=dataclasses.replace(config.training, encoder=encoder))
    if output_dir is not None:
        config = dataclasses.replace(
            config, outputs=dataclasses.replace(config.outputs, output_dir=output_dir))
    if seed is not None:
        config = dataclasses.replace(config, seed=seed)
    if data is not None:
        config = dataclasses.replace(config, data=data)
    return config
