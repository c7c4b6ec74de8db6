"""A backtest's settings: its horizons, levels and seed, the published combiner, the variants
scored beside it (:class:`Variant`), its sample paths and the members' time limit."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from pipeline.combine.average import EnsembleError, WeightMethod
from pipeline.combine.combiner import CombineConfig
from pipeline.combine.plausibility import PlausibilityConfig
from pipeline.panels.targets import HORIZONS_WEEKS, HUB_QUANTILE_LEVELS


@dataclass(frozen=True)
class Variant:
    """A design alternative scored beside the published forecast: another combiner over the
    same members, or the published combiner over a subset of them (``members``)."""

    name: str
    combine: CombineConfig = field(default_factory=CombineConfig)
    members: tuple[str, ...] | None = None


# the single online calibrations: η = 0.15 (published until 2026-11-29), a third and twice it
TRACKING_RATE_VARIANTS = (0.05, 0.15, 0.3)


def tracking_rate_variants(published: CombineConfig, prefix: str = "v-") -> tuple[Variant, ...]:
    """The published combiner with one adaptive conformal tracker (``"regime-aci"``, its misses
    not standardized) at each η of :data:`TRACKING_RATE_VARIANTS` in place of the aggregate,
    named ``<prefix>regime-aci eta=<η>`` (every panel's backtest scores them beside it)."""
    return tuple(Variant(f"{prefix}regime-aci eta={rate}", dataclasses.replace(
        published, calibration="regime-aci", tracking_rate=rate, tracking_standardized=False))
                 for rate in TRACKING_RATE_VARIANTS)


# calibrations that let go of a past surge (issue 51): the experts' losses and coverage
# forgotten with a half-life of 4 origins, or each stretch let go by 10 % at every origin
FORGETTING_HALF_LIFE_ORIGINS = 4.0
STRETCH_LEAK = 0.1


def letting_go_variants(published: CombineConfig, prefix: str = "v-") -> tuple[Variant, ...]:
    """The published combiner with a calibration that forgets: the aggregate's experts chosen
    on the outcomes of the last origins more than the older ones
    (:data:`FORGETTING_HALF_LIFE_ORIGINS`), and each expert's stretch fading when nothing renews
    it (:data:`STRETCH_LEAK`); the stretch acting on values about the median alone; and the two
    rules published before it: the stretch acting on levels of the quantile function (published
    until 4f1f7d6), and on levels with the aggregate's published weights jumping with its
    choice (published until 2026-11-30, 66a41c0), named ``<prefix>calibration …`` (every
    panel's backtest scores them beside it)."""
    on_levels = dataclasses.replace(published, tracking_space="levels")
    return (Variant(f"{prefix}calibration switching at once (published until 2026-11-30)",
                    dataclasses.replace(on_levels, aggregation_smoothing_origins=None)),
            Variant(f"{prefix}calibration stretching levels (published until 4f1f7d6)",
                    on_levels),
            Variant(f"{prefix}calibration stretching values about the median",
                    dataclasses.replace(published, tracking_space="values")),
            Variant(f"{prefix}calibration forgetting (half-life "
                    f"{FORGETTING_HALF_LIFE_ORIGINS:g} origins)", dataclasses.replace(
                        published, aggregation_memory_origins=FORGETTING_HALF_LIFE_ORIGINS)),
            Variant(f"{prefix}calibration letting go ({STRETCH_LEAK:.0%} of a stretch a week)",
                    dataclasses.replace(published, tracking_leak=STRETCH_LEAK)))


def bound_variants(published: CombineConfig, prefix: str = "v-") -> tuple[Variant, ...]:
    """The published combiner without its bound on falls, and with the rises bounded too
    (:mod:`pipeline.combine.plausibility`), named ``<prefix>published, …`` (every panel's
    backtest scores them beside it)."""
    return (Variant(f"{prefix}published, unbounded", dataclasses.replace(published,
                                                                         bounded=None)),
            Variant(f"{prefix}published, rises bounded too",
                    dataclasses.replace(published, bounded=PlausibilityConfig())))


def skill_weighted_variants(published: CombineConfig, members: tuple[str, ...],
                            methods: tuple[WeightMethod, ...] = ("inverse-wis", "stacking"),
                            prefix: str = "v-") -> tuple[Variant, ...]:
    """The published combiner over ``members`` weighted by their skill on the rounds already
    scored: by inverse WIS, and by stacking (weights minimising the past rounds' WIS: a simplex
    grid, for a few members only), each over its window of origins
    (:class:`~pipeline.combine.combiner.CombineConfig`)."""
    joined = "+".join(members)
    # a grid of tenths: 66 weightings of three members (twentieths: 231, each a mixture to
    # score at every origin and horizon)
    return tuple(Variant(f"{prefix}{weights} {joined}",
                         dataclasses.replace(published, weights=weights, stacking_step=0.1),
                         members)
                 for weights in methods)


@dataclass(frozen=True)
class BacktestConfig:
    """Horizons (weeks after each origin), levels, the members' seed, the published combiner,
    the variants scored beside it, and the published forecast's sample paths per cell (0: none;
    their ranks follow the first member that simulates paths)."""

    horizons: tuple[int, ...] = HORIZONS_WEEKS
    levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    seed: int = 0
    combine: CombineConfig = field(default_factory=CombineConfig)
    variants: tuple[Variant, ...] = ()
    n_paths: int = 0
    # a member still forecasting after this long is left out (pipeline.members.isolation);
    # the slowest, nf-weekly's 1,000 draws over 44 rounds × 53 places, takes about a minute
    member_time_limit_s: float | None = 1800.0

    def __post_init__(self) -> None:
        if not self.horizons or min(self.horizons) < 1:
            raise EnsembleError(f"horizons {self.horizons} must be weeks >= 1")
        if self.n_paths < 0:
            raise EnsembleError(f"n_paths={self.n_paths} must be >= 0")
