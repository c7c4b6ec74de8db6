"""The settings of each step of the weekly run, one frozen dataclass a step: the joint models'
training, the estimates, the rollouts, the NF-seeded SMC, the nowcast of the days still being
reported, and the run's files (:class:`~pipeline.forecast.config.ForecastConfig` nests them).
Each checks its own values on construction (:class:`~pipeline.errors.ConfigError`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pipeline.data.california.delays import DelayModelConfig
from pipeline.errors import ConfigError

# How forward rollouts carry the flow's estimate past the anchor (pipeline.inference.seeded_rollout)
ForwardRollout = Literal["flow-seeded-prior", "chained-flow"]
FORWARD_ROLLOUTS: tuple[ForwardRollout, ...] = ("flow-seeded-prior", "chained-flow")

def _require_positive(owner: str, **values: int | None) -> None:
    for name, value in values.items():
        if value is not None and value < 1:
            raise ConfigError(f"{owner}.{name}={value} must be >= 1")


@dataclass(frozen=True)
class NowcastSettings:
    """The nowcast of the days still being reported (``pipeline.forecast.nowcasting``).

    ``completions``: K nowcast samples of the recent days, each forecast, mixed (the nowcast
    itself draws ``nowcast_samples``, for its own quantiles and the hub file); the delay model
    is fitted (and cached) from every CDPH vintage in the data cache plus the CDPH downloads in
    ``archive`` folders (the flow fills them from ``$FLOWCAST_CDPH_ARCHIVE``, colon-separated). With fewer than
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
