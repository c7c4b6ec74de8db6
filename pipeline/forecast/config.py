"""What determines one weekly run: typed sub-configs, the named presets, and their resolution.

:class:`ForecastConfig` nests one frozen dataclass per concern (data, training, estimates,
rollouts, SMC, the published forecast, outputs). The training presets and the SIR prior they
imply are resolved once per config (:attr:`ForecastConfig.resolved`), not at every use.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

from pipeline.data.california.counties import SAN_FRANCISCO, california_county
from pipeline.data.california.delays import DelayModelConfig
from pipeline.backtest.track_record import TrackRecordConfig
from pipeline.members.nf.model import GrowthModelConfig
from pipeline.members.nf.finetune import FineTuneConfig
from pipeline.members.published import MembersConfig
from pipeline.errors import ConfigError
from pipeline.names import DIRECTIONS, Direction
from pipeline.systems.waves import WavePrior, recovery_rate
from pipeline.training.presets import TrainingPreset, get_preset

DataSourceKind = Literal["live", "cache", "import"]
# How forward rollouts carry the flow's estimate past the anchor (pipeline.inference.seeded_rollout)
ForwardRollout = Literal["flow-seeded-prior", "chained-flow"]
FORWARD_ROLLOUTS: tuple[ForwardRollout, ...] = ("flow-seeded-prior", "chained-flow")
SeedStep = Literal["simulate", "train_forward", "train_backward", "latest", "rollout", "future",
                   "params", "nll", "smc", "weekly", "train_growth", "nowcast"]
# Per-step seed offsets: changing one step's draws never shifts another's.
_SEED_OFFSETS: dict[SeedStep, int] = {
    "simulate": 0, "train_forward": 11, "train_backward": 12, "latest": 21, "rollout": 31,
    "future": 41, "params": 51, "nll": 61, "smc": 71, "weekly": 91, "train_growth": 92,
    "nowcast": 93}


def _require_positive(owner: str, **values: int | None) -> None:
    for name, value in values.items():
        if value is not None and value < 1:
            raise ConfigError(f"{owner}.{name}={value} must be >= 1")


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
class NowcastSettings:
    """The nowcast of the days still being reported (``pipeline.forecast.nowcasting``).

    ``completions``: K nowcast samples of the recent days, each forecast, mixed (the nowcast
    itself draws ``nowcast_samples``, for its own quantiles and the hub file); the delay model
    is fitted (and cached) from every CDPH vintage in the data cache plus the CDPH downloads in
    ``archive`` folders (default ``$FLOWCAST_CDPH_ARCHIVE``, colon-separated). With fewer than
    two vintages there is no delay model: the run drops ``fallback_trailing_days`` instead, as
    it did before, and says so."""

    enabled: bool = True
    completions: int = 32
    nowcast_samples: int = 256
    archive: tuple[str, ...] = ()
    fallback_trailing_days: int = 14
    mixture_weeks: int = 4          # origins this many weeks back (and later) use completions
    delay: DelayModelConfig = field(default_factory=DelayModelConfig)

    def __post_init__(self) -> None:
        _require_positive("NowcastSettings", completions=self.completions,
                          mixture_weeks=self.mixture_weeks)
        if self.nowcast_samples < self.completions:
            raise ConfigError("NowcastSettings.nowcast_samples must be >= completions")
        if self.fallback_trailing_days < 0:
            raise ConfigError("NowcastSettings.fallback_trailing_days must be >= 0")


@dataclass(frozen=True)
class TrainingSettings:
    """The joint models: one named training preset (:func:`pipeline.training.presets.get_preset`,
    ``preset`` × ``encoder`` × ``recipe``, one per direction) — the single source of the dataset,
    estimator and optimiser settings. They train on the multi-wave prior of the published
    forecast's flow member (``ForecastConfig.weekly.growth.prior``): one model of the epidemic.
    The optional sizes only shrink it (None = the preset's), so the ``tiny`` forecast is the same
    model family at toy size."""

    preset: str = "sf-waves-joint"
    recipe: str = "fast"
    # An MLP over two weeks of S/I/R: the transformer took 594 s of a 706 s run to train and,
    # on this 14-row window, has nothing to attend to that the MLP misses (docs/models.md).
    encoder: str = "mlp"
    n_trajectories: int | None = None
    iterations: int | None = None
    batch_size: int | None = None
    eval_every: int | None = None
    # When the pair must be trained, the forecast's own models train meanwhile in a background
    # process (pipeline.forecast.member_training); the same models either way. Off for toy
    # sizes, where starting a second Python costs more than their training.
    background_members: bool = True

    def __post_init__(self) -> None:
        _require_positive("TrainingSettings", n_trajectories=self.n_trajectories,
                          iterations=self.iterations,
                          batch_size=self.batch_size, eval_every=self.eval_every)


@dataclass(frozen=True)
class EstimateSettings:
    n_samples: int = 500            # draws per estimate
    parameter_stride_days: int = 3  # β, R_t track: one estimate every this many days
    nll_locations: int = 100        # random SF days scored by the NLL table

    def __post_init__(self) -> None:
        _require_positive("EstimateSettings", n_samples=self.n_samples,
                          parameter_stride_days=self.parameter_stride_days,
                          nll_locations=self.nll_locations)


@dataclass(frozen=True)
class RolloutSettings:
    windows: tuple[int, ...] = (7, 28)
    # Rolling rollouts cover the whole history (~740 days x 4 views), one flow call per day for
    # every anchor x path; the future paths use ``future_paths``.
    paths: int = 128
    forecast_days: int = 28         # the paper's rollout forecast past the last observed day
    future_paths: int = 200
    # Forward: the flow's (S, I, R, β) at the anchor carried on by the prior's dynamics; the
    # chained flow overshot SF's Omicron peak 2.3-4.0x depending on the training seed
    # (pipeline.inference.seeded_rollout). Backward rollouts are always chained.
    forward: ForwardRollout = "flow-seeded-prior"
    # Correlation of a chained path's flow noise from one day to the next (inference.rollout):
    # with fresh noise every day a path forgets which transmission rate it drew. bench/
    # rollouts_sf.py, 90 % bands of the backward 28-day rollout: 0 covers 75 % of the prior's
    # synthetic paths and 63 % of SF's days, 0.5 92 % / 84 %, 0.7 95 % / 88 %. SF's own series
    # is the harder one; 0.7 keeps it above 85 % for every training seed (bench.calibration).
    noise_persistence: float = 0.7

    def __post_init__(self) -> None:
        if any(w < 1 for w in self.windows):
            raise ConfigError(f"RolloutSettings.windows={self.windows} must all be >= 1")
        if self.forward not in FORWARD_ROLLOUTS:
            raise ConfigError(f"RolloutSettings.forward={self.forward!r}: choose one of "
                              f"{', '.join(FORWARD_ROLLOUTS)}")
        if not 0.0 <= self.noise_persistence <= 1.0:
            raise ConfigError(f"RolloutSettings.noise_persistence={self.noise_persistence} "
                              "must lie in [0, 1]")
        _require_positive("RolloutSettings", paths=self.paths, forecast_days=self.forecast_days,
                          future_paths=self.future_paths)


@dataclass(frozen=True)
class SMCSettings:
    """The NF-seeded filter on the multi-wave model (:mod:`pipeline.inference.hybrid`): its
    particle count and the days it filters; its forecast member is scored in the backtest."""

    particles: int = 1000
    days: int = 56                  # observations the seeded filter runs over
    member_particles: int = 500     # per origin, in the backtest's batch of filters

    def __post_init__(self) -> None:
        _require_positive("SMCSettings", particles=self.particles, days=self.days,
                          member_particles=self.member_particles)


@dataclass(frozen=True)
class OutputSettings:
    output_dir: str = "reports"     # <output_dir>/<reference-date>/ per run, plus index.html
    hub_samples: int = 200          # sample paths per target in the hubverse file (at most)

    def __post_init__(self) -> None:
        _require_positive("OutputSettings", hub_samples=self.hub_samples)


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
    # prior, few iterations, samples, particles and backtest origins.
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
                                  finetune=FineTuneConfig(iterations=10, refit_every_weeks=26)),
            n_paths=100),
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
