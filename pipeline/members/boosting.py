"""A gradient-boosted quantile member pooled over every place of a panel (``gbqr``).

The leading hub teams' recipe (UMass's ``gbqr`` and Flusion, Ray et al., *Epidemics* 2024): one
model over all locations, on a variance-stabilised scale, trained afresh at each origin on what
its vintage held then, with the quantile loss.

* **Scale.** A place's weekly count becomes a rate per 100,000 of its population, then its
  fourth root z (counts of any size vary alike on it; Flusion's transform), then u = z / s with
  s the place's ``scale_quantile`` of z over its history known at the origin: the US and a small
  state, a quiet season and a busy one, on one scale.
* **Features** at week t: u_t; z_t (how high the rate is in absolute terms); the changes of u
  over 1, 2 and 4 weeks; the slope and curvature of a quadratic through the last
  ``local_weeks`` weeks; the week of the year (as a sine and cosine); log population; the
  horizon h.
* **Target**: u_{t+h} − u_t, one LightGBM model per fitted level (``fitted_levels``) with the
  quantile (pinball) loss, fitted on every (place, week, horizon) whose target week had ended
  by the origin. Its predictions are sorted across levels (no quantile crossing), added to the
  place's u at the origin and mapped back to counts; the levels asked are read from the
  continuous quantile function through the fitted ones (log-normal-like tails).

The places' own histories at the origin (the nowcast's median where the engine nowcasts) give
the rows predicted; the pool's rows train. Nothing after the origin enters, in any place.

**The other signal** (``other``: the hub's ED share beside admissions, admissions beside the
share; Flusion's several sources; without ``other``, the panel's own ``signal``: California's
test positivity beside the cases): its vintage as released by the cell's panel's release date
(``as_of``) adds (a) its level and changes over 1 and 2 weeks at the same place and week as
features (missing where it has no such week), and (b) its own series as training rows, with an
indicator of the signal, each signal's row weights averaging 1: admissions, reported since
2024-11, learn from the share's curves since 2022-10.
"""
from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.errors import ConfigError
from pipeline.evaluation.quantile_function import quantiles_at
from pipeline.members.base import ForecastsByPool, PoolGroup
from pipeline.panels.panel import Panel, known_by
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError

GBQR = "gbqr"
PER_100K = 1e5
WEEKS_PER_YEAR = 365.25 / 7


@dataclass(frozen=True)
class BoostingConfig:
    """The scale (``rate_offset`` per 100,000 before the fourth root; ``scale_quantile``), the
    local fit's ``local_weeks``, LightGBM's settings, and ``min_rows`` training rows below which
    the member forecasts no change with the spread of the changes seen so far."""

    rate_offset: float = 0.01
    scale_quantile: float = 0.95
    local_weeks: int = 6
    n_estimators: int = 100
    # the hubs' trees; California's panels grow LightGBM's own since 2026-12-01 (deep_trees)
    learning_rate: float = 0.05
    num_leaves: int = 15
    min_child_samples: int = 40
    subsample: float = 0.7
    colsample: float = 0.8
    min_rows: int = 200
    # training rows weighted by population ** weight_power (0: every place alike)
    weight_power: float = 0.5
    # the levels a model is fitted at; the others asked are read from the continuous quantile
    # function through them (pipeline.evaluation.quantile_function): a model per level is the
    # member's cost, and the hub's 23 cost 3.3 times these 7
    fitted_levels: tuple[float, ...] = (0.025, 0.1, 0.25, 0.5, 0.75, 0.9, 0.975)
    seed: int = 0

    def __post_init__(self) -> None:
        if (self.rate_offset <= 0 or not 0 < self.scale_quantile <= 1 or self.local_weeks < 3
                or self.n_estimators < 1 or self.learning_rate <= 0 or self.num_leaves < 2
                or self.min_child_samples < 1 or not 0 < self.subsample <= 1
                or not 0 < self.colsample <= 1 or self.min_rows < 1
                or len(self.fitted_levels) < 2 or list(self.fitted_levels) != sorted(
                    set(self.fitted_levels)) or not 0 < self.fitted_levels[0]
                or not self.fitted_levels[-1] < 1):
            raise ConfigError(f"invalid BoostingConfig {self}")


@dataclass(frozen=True, eq=False)
class Scaled:
    """A block of series on the member's scale: ``z`` (P, W) the fourth root of the rate,
    ``u`` = z / ``scale`` (P, 1)."""

    z: NDArray[np.float64]
    scale: NDArray[np.float64]
    population: NDArray[np.float64]

    @property
    def u(self) -> NDArray[np.float64]:
        return self.z / self.scale


def scaled(weekly: NDArray[np.float64], population: NDArray[np.float64],
           config: BoostingConfig) -> Scaled:
    """``weekly (P, W)`` counts on the member's scale (module docstring)."""
    rate = np.maximum(weekly, 0.0) / population[:, None] * PER_100K
    z = (rate + config.rate_offset) ** 0.25
    with warnings.catch_warnings():                  # a place with no week observed: NaN scale
        warnings.simplefilter("ignore", RuntimeWarning)
        scale = np.nanquantile(np.where(np.isfinite(z), z, np.nan), config.scale_quantile,
                               axis=1, keepdims=True)
    floor = config.rate_offset ** 0.25               # a place never above the offset
    return Scaled(z, np.maximum(np.nan_to_num(scale, nan=1.0), 2 * floor), population)


def counts_of(u: NDArray[np.float64], block: Scaled, config: BoostingConfig
              ) -> NDArray[np.float64]:
    """Counts of ``u (P, ...)`` on ``block``'s scale: the inverse of :func:`scaled`."""
    shape = (-1,) + (1,) * (u.ndim - 1)
    z = np.maximum(u * block.scale.reshape(shape), 0.0)
    rate = np.maximum(z ** 4 - config.rate_offset, 0.0)
    return rate * block.population.reshape(shape) / PER_100K


def _change(u: NDArray[np.float64], lag: int) -> NDArray[np.float64]:
    out = np.full_like(u, np.nan)
    out[:, lag:] = u[:, lag:] - u[:, :-lag]
    return out


def _local_fit(u: NDArray[np.float64], weeks: int) -> NDArray[np.float64]:
    """``(P, W, 2)``: slope and curvature of the least-squares quadratic through each week's
    last ``weeks`` weeks (x = 0 at the week itself)."""
    x = np.arange(-weeks + 1, 1, dtype=np.float64)
    design = np.stack([np.ones_like(x), x, x ** 2], axis=1)
    solve = np.linalg.pinv(design)[1:]                                     # (2, weeks)
    out = np.full(u.shape + (2,), np.nan)
    if u.shape[1] >= weeks:
        windows = np.lib.stride_tricks.sliding_window_view(u, weeks, axis=1)  # (P, W-k+1, k)
        out[:, weeks - 1:] = windows @ solve.T
    return out


FEATURES = ("u", "z", "change_1", "change_2", "change_4", "slope", "curvature", "season_sin",
            "season_cos", "log_population", "horizon")
# with another signal, before the horizon: which signal the row is (0 the target's own), and
# the other signal's u and its changes over 1 and 2 weeks at the same place and week
OTHER_FEATURES = ("signal", "other_u", "other_change_1", "other_change_2")
_READ_BY_THE_OTHER = [FEATURES.index(n) for n in ("u", "change_1", "change_2")]


def features(block: Scaled, week_ends: pd.DatetimeIndex, config: BoostingConfig
             ) -> NDArray[np.float64]:
    """``(P, W, F-1)``: :data:`FEATURES` but the horizon, at every week."""
    u = block.u
    n_p, n_w = u.shape
    phase = 2 * np.pi * np.asarray(week_ends.dayofyear, dtype=np.float64) / 365.25
    columns = [u, block.z, _change(u, 1), _change(u, 2), _change(u, 4)]
    local = _local_fit(u, config.local_weeks)
    columns += [local[..., 0], local[..., 1],
                np.broadcast_to(np.sin(phase), (n_p, n_w)),
                np.broadcast_to(np.cos(phase), (n_p, n_w)),
                np.broadcast_to(np.log(block.population)[:, None], (n_p, n_w))]
    return np.stack(columns, axis=-1)


@dataclass(frozen=True, eq=False)
class TrainingRows:
    """Features ``x (N, F)``, changes ``y (N,)`` and weights ``weight (N,)``."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    weight: NDArray[np.float64]


def training_rows(block: Scaled, x: NDArray[np.float64], horizons: Sequence[int],
                  config: BoostingConfig) -> TrainingRows:
    """Every (place, week t, horizon h) whose week t + h is held: features with h, and the
    change u_{t+h} − u_t."""
    u = block.u
    n_p, n_w = u.shape
    place_weight = block.population ** config.weight_power
    xs, ys, ws = [], [], []
    for h in horizons:
        if n_w <= h:
            continue
        y = (u[:, h:] - u[:, :n_w - h]).reshape(-1)
        rows = x[:, :n_w - h].reshape(-1, x.shape[-1])
        keep = np.isfinite(y) & np.isfinite(rows[:, 0])
        xs.append(np.column_stack([rows[keep], np.full(keep.sum(), float(h))]))
        ys.append(y[keep])
        ws.append(np.repeat(place_weight, n_w - h)[keep])
    if not xs:
        return TrainingRows(np.empty((0, x.shape[-1] + 1)), np.empty(0), np.empty(0))
    weight = np.concatenate(ws)
    return TrainingRows(np.concatenate(xs), np.concatenate(ys),
                        weight / weight.mean() if weight.size else weight)


def fit_predict(rows: TrainingRows, x_now: NDArray[np.float64], levels: NDArray[np.float64],
                config: BoostingConfig, seed: int) -> NDArray[np.float64]:
    """``(N, Q)`` predicted quantiles of the change at the rows ``x_now``, sorted across
    levels: one quantile-loss model per level on one binned dataset."""
    import lightgbm as lgb

    if len(rows.y) < config.min_rows:
        spread = np.quantile(rows.y, levels) if len(rows.y) else np.zeros(len(levels))
        return np.broadcast_to(spread, (len(x_now), len(levels))).copy()
    data = lgb.Dataset(rows.x, rows.y, weight=rows.weight, params={"verbose": -1, "max_bin": 63},
                       free_raw_data=False)
    out = np.empty((len(x_now), len(levels)))
    for k, level in enumerate(levels):
        params = {"objective": "quantile", "alpha": float(level),
                  "learning_rate": config.learning_rate, "num_leaves": config.num_leaves,
                  "min_child_samples": config.min_child_samples,
                  "bagging_fraction": config.subsample, "bagging_freq": 1,
                  "feature_fraction": config.colsample, "seed": seed, "deterministic": True,
                  "num_threads": 1, "verbose": -1, "max_bin": 63}
        booster = lgb.train(params, data, num_boost_round=config.n_estimators)
        out[:, k] = np.asarray(booster.predict(x_now), dtype=np.float64)
    return np.sort(out, axis=1)


def last_finite(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(P,)`` each row's last finite value (0 for a row with none)."""
    finite = np.isfinite(values)
    last = values.shape[1] - 1 - np.argmax(finite[:, ::-1], axis=1)
    return np.where(finite.any(axis=1), values[np.arange(len(values)), last], 0.0)


def boosting_seed(config: BoostingConfig, origin: pd.Timestamp) -> int:
    """The models' seed at ``origin``: the same whichever cells are forecast with it."""
    return int(np.random.SeedSequence([config.seed, origin.toordinal()])
               .generate_state(1)[0] % (2 ** 31))


def _week_ends(origin: pd.Timestamp, n_weeks: int) -> pd.DatetimeIndex:
    return pd.DatetimeIndex([origin - pd.Timedelta(days=DAYS_PER_WEEK * (n_weeks - 1 - i))
                             for i in range(n_weeks)])


def right_aligned(values: NDArray[np.float64], n_weeks: int) -> NDArray[np.float64]:
    """``values (P, W, ...)`` over the weeks ending the origin, as the last ``n_weeks`` of
    them: cut on the left, or NaN before its first week."""
    if values.shape[1] >= n_weeks:
        return values[:, values.shape[1] - n_weeks:]
    pad = np.full((values.shape[0], n_weeks - values.shape[1], *values.shape[2:]), np.nan)
    return np.concatenate([pad, values], axis=1)


@dataclass(frozen=True, eq=False)
class Signal:
    """One signal's places on the member's scale over the weeks ending the origin, with their
    :func:`features`."""

    places: list[str]
    block: Scaled
    x: NDArray[np.float64]

    @classmethod
    def of(cls, weekly: NDArray[np.float64], places: list[str],
           population: NDArray[np.float64], origin: pd.Timestamp, config: BoostingConfig
           ) -> Signal:
        block = scaled(weekly, population, config)
        return cls(places, block, features(block, _week_ends(origin, weekly.shape[1]), config))

    def levels_at(self, places: Sequence[str], n_weeks: int) -> NDArray[np.float64]:
        """``(len(places), n_weeks, 3)``: this signal's u and its changes over 1 and 2 weeks
        at ``places`` over the last ``n_weeks`` weeks (NaN at a place it does not have)."""
        row = {p: i for i, p in enumerate(self.places)}
        mine = right_aligned(self.x[..., _READ_BY_THE_OTHER], n_weeks)
        out = np.full((len(places), n_weeks, 3), np.nan)
        found = [k for k, p in enumerate(places) if p in row]
        out[found] = mine[[row[places[k]] for k in found]]
        return out


def with_other(x: NDArray[np.float64], signal: float, other: NDArray[np.float64]
               ) -> NDArray[np.float64]:
    """``x (P, W, F0)`` with :data:`OTHER_FEATURES`: the row's ``signal`` and ``other``."""
    return np.concatenate([x, np.full(x.shape[:2] + (1,), signal), other], axis=-1)


def both_signals_rows(own: Signal, other: Signal, horizons: Sequence[int],
                      config: BoostingConfig) -> TrainingRows:
    """The training rows of the target's pool and of the other signal's (module docstring),
    each reading the other at the same place and week; each signal's weights average 1."""
    n_own, n_other = own.x.shape[1], other.x.shape[1]
    parts = [training_rows(own.block, with_other(own.x, 0.0, other.levels_at(own.places, n_own)),
                           horizons, config),
             training_rows(other.block,
                           with_other(other.x, 1.0, own.levels_at(other.places, n_other)),
                           horizons, config)]
    parts = [p for p in parts if len(p.y)]
    if not parts:
        return TrainingRows(np.empty((0, own.x.shape[-1] + len(OTHER_FEATURES) + 1)),
                            np.empty(0), np.empty(0))
    return TrainingRows(np.concatenate([p.x for p in parts]),
                        np.concatenate([p.y for p in parts]),
                        np.concatenate([p.weight for p in parts]))


def weeks_since_first(panel: Panel, origin: pd.Timestamp) -> int:
    """The weeks ending ``origin`` back to ``panel``'s first day (at least 1)."""
    return max((origin - panel.first_date).days // DAYS_PER_WEEK + 1, 1)


@dataclass(frozen=True, eq=False)
class PooledBoostingMember(ForecastsByPool):
    """``gbqr`` (module docstring): one set of quantile models per panel and origin, trained
    on the panel's pool as known at the origin, predicting every cell from its own history;
    with ``other`` (the other signal's vintages by release date), on both signals."""

    config: BoostingConfig = BoostingConfig()
    name: str = GBQR
    other: Sequence[tuple[pd.Timestamp, Panel]] = ()
    # without ``other``: read the panel's own signal (False: the target's series alone)
    reads_panel_signal: bool = True
    pools: ClassVar[bool] = True          # learns from the cell's panel (the memo keys on it)

    def other_for(self, panel: Panel) -> Panel | None:
        """The other signal as released by ``panel``'s release date (none before its first);
        without ``other``, the panel's own :attr:`~Panel.signal` (the same download's)."""
        if not self.other:
            return panel.signal if self.reads_panel_signal else None
        if panel.as_of is None:
            raise TargetError(f"{self.name}: the cell's panel has no release date to choose "
                              "the other signal known then")
        return known_by(sorted(self.other, key=lambda v: v[0]), panel.as_of)

    def cell_identity(self, origin: pd.Timestamp, panel: Panel) -> object:
        """What a cell reads beyond its panel (:class:`~pipeline.members.base.KeyedByCell`):
        the settings and the other signal as released by the panel's date."""
        return (self.name, self.config, self.other_for(panel))

    def group_forecast(self, group: PoolGroup, horizons: tuple[int, ...],
                       levels: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(B, H, Q)`` counts of the group's cells."""
        origin, n_weeks, own = group.origin, group.n_weeks, group.own
        pool = Signal.of(group.pool, group.panel.pool_places(group.places[0]),
                         group.panel.pool_populations(group.places[0]), origin, self.config)
        mine = Signal.of(np.stack(own), list(group.places), group.populations, origin,
                         self.config)
        now = mine.x[:, -1]                                                # (B, F0)
        source = self.other_for(group.panel)
        if source is None:
            rows = training_rows(pool.block, pool.x, horizons, self.config)
        else:
            place = group.places[0]
            weeks = max(weeks_since_first(source, origin), n_weeks)
            other = Signal.of(source.pool(place, origin, weeks), source.pool_places(place),
                              source.pool_populations(place), origin, self.config)
            rows = both_signals_rows(pool, other, horizons, self.config)
            now = with_other(mine.x[:, -1:], 0.0, other.levels_at(mine.places, 1))[:, 0]
        n_b, n_h = len(own), len(horizons)
        x_now = np.column_stack([np.repeat(now, n_h, axis=0),
                                 np.tile(np.asarray(horizons, dtype=np.float64), n_b)])
        fitted = np.asarray(self.config.fitted_levels, dtype=np.float64)
        change = fit_predict(rows, x_now, fitted, self.config,
                             boosting_seed(self.config, origin))
        u_now = last_finite(mine.block.u)
        u = u_now[:, None, None] + change.reshape(n_b, n_h, len(fitted))
        return np.maximum.accumulate(quantiles_at(fitted, counts_of(u, mine.block, self.config),
                                                  levels), axis=-1)


# gbqr with the trees it does not publish, scored beside the published gbqr by the benches:
# the shallow trees on California's panels (published there until 79ea0ca), the deep trees on
# the hubs (docs/forecasting.md, "gbqr's trees")
SHALLOW_GBQR = "gbqr-shallow"
DEEP_GBQR = "gbqr-deep"


def deep_trees(config: BoostingConfig) -> BoostingConfig:
    """``config`` with LightGBM's own trees, 31 leaves at a learning rate of 0.1: California's
    gbqr since 2026-12-01. On the hubs they bought skill with coverage."""
    return dataclasses.replace(config, learning_rate=0.1, num_leaves=31)


def the_gbqr(members: Sequence[object]) -> PooledBoostingMember:
    """The member named :data:`GBQR` among ``members``."""
    found = [m for m in members if isinstance(m, PooledBoostingMember) and m.name == GBQR]
    if len(found) != 1:
        raise ConfigError(f"expected one {GBQR} member, found {len(found)}")
    return found[0]
