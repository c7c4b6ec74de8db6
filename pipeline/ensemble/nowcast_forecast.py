"""Nowcast, then forecast, from the data date: which weeks are nowcast, which are forecast, and
the forecast's predictive distribution mixed over the nowcast's completions.

**Weeks.** The data date D is the last day in the data. The hub round's reference date is the
Saturday ending D's epiweek (D itself on a Saturday); the origin is the last Saturday ≤ D. Hub
horizon h is the epiweek ending ``reference + 7h``: a week ending on or before the origin lies
wholly in the data and is **nowcast** (its final count from the nowcast's samples); a later week
is **forecast**, ``(end − origin)/7`` weeks after the origin (1..4 for hub horizons 0..3, the
four weeks the flow member forecasts).

**The days after the origin.** When D is not a Saturday, the current week (hub horizon 0) has
its first days in the data. By default the week is the forecast's week from the origin (which
the weekly run publishes too), raised to at least the cases already reported for those days
(:func:`floor_current_week`: a week cannot end below what has been reported in it; before, the
weekly run's 5 % quantile of the current week, 93 cases, lay below the 321 already reported for
its first four days). ``partial_week=True`` makes it the nowcast of
those days plus the forecast's week scaled by the share of a week's cases its other days carry
(weekday shares of the completed history's last eight weeks; a monotone map of the forecast, so
quantiles map exactly). Measured on the CDPH vintages (``bench/nowcast.py``) it did worse: those
days are the least complete, and their nowcast the least certain.

**Mixing.** Each completion k of the nowcast is forecast as a history of its own (one batch);
the published distribution is their equal mixture: each completion's continuous quantile
function (:func:`pipeline.ensemble.calibration.quantiles_at`) is read at the same stratified
levels, the draws are pooled and the hub quantiles taken from the pool — the average of the
CDFs, not of the quantiles.

:class:`CompletionForecaster` is the small protocol behind which any weekly forecaster is
plugged in (AutoETS in the benchmark; the published ensemble in the weekly run).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, TypeVar, runtime_checkable

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.ensemble.calibration import quantiles_at
from pipeline.ensemble.members import Member, quantile_forecast_from_weekly_cases
from pipeline.ensemble.nowcast import CompletedHistories, Nowcast, complete_histories
from pipeline.ensemble.panel import BatchMember, forecast_cells
from pipeline.ensemble.targets import DAYS_PER_WEEK, EpiHistory, QuantileForecast, TargetError
from pipeline.evaluation.scoring import quantiles_from_samples

SATURDAY = 5
HUB_HORIZONS: tuple[int, ...] = (-1, 0, 1, 2, 3)
MIX_LEVELS = 200
WEEKDAY_SHARE_WEEKS = 8
WeekKind = Literal["nowcast", "forecast"]
Place = TypeVar("Place", str, None)          # a place's name (None: one unnamed place)


class CompletionForecaster(Protocol):
    """Weekly case quantiles ``(B, H, Q)`` of B histories at weekly steps ``horizons`` after
    each history's last day (its origin); ``places[b]`` names history b's place (a pooled
    forecaster leaves the place's own reference series out of its pool)."""

    @property
    def name(self) -> str: ...

    def __call__(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int,
                 places: Sequence[str | None] | None = None) -> NDArray[np.float64]: ...


@runtime_checkable
class MemberwiseForecaster(CompletionForecaster, Protocol):
    """An ensemble whose members' quantiles ``(M, B, H, Q)`` and their combination are exposed:
    a nowcast's completions are then mixed per member before the members are combined, as the
    weekly run's :class:`CompletionMixture` does."""

    def member_quantiles(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                         levels: NDArray[np.float64], seed: int,
                         places: Sequence[str | None] | None = None
                         ) -> NDArray[np.float64]: ...

    def combine(self, member_quantiles: NDArray[np.float64]) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class MemberForecaster:
    """A weekly :class:`~pipeline.ensemble.members.Member` (or a batch member) as a
    :class:`CompletionForecaster`."""

    member: Member | BatchMember

    @property
    def name(self) -> str:
        return self.member.name

    def __call__(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int,
                 places: Sequence[str | None] | None = None) -> NDArray[np.float64]:
        return forecast_cells(self.member, histories, horizons, levels, seed)["cases"]


# --------------------------------------------------------------------------------- weeks


def last_saturday(date: pd.Timestamp) -> pd.Timestamp:
    """The last Saturday on or before ``date``."""
    d = pd.Timestamp(date).normalize()
    return d - pd.Timedelta(days=(d.weekday() - SATURDAY) % DAYS_PER_WEEK)


def reference_date(data_date: pd.Timestamp) -> pd.Timestamp:
    """The Saturday ending the epiweek (Sunday–Saturday) that holds ``data_date``."""
    d = pd.Timestamp(data_date).normalize()
    return d + pd.Timedelta(days=(SATURDAY - d.weekday()) % DAYS_PER_WEEK)


@dataclass(frozen=True)
class HubWeek:
    """One hub horizon: its week's last day, nowcast or forecast, and (forecast) the step in
    weeks after the origin."""

    horizon: int
    end: pd.Timestamp
    kind: WeekKind
    step: int            # weeks after the origin (≤ 0: a nowcast week)


@dataclass(frozen=True)
class HubWeeks:
    """The weeks of a round with data up to ``data_date`` (module docstring)."""

    data_date: pd.Timestamp
    origin: pd.Timestamp
    reference: pd.Timestamp
    weeks: tuple[HubWeek, ...]

    @property
    def forecast_steps(self) -> tuple[int, ...]:
        return tuple(w.step for w in self.weeks if w.kind == "forecast")

    @property
    def known_days_after_origin(self) -> int:
        """Days of the current week in the data (0 when the data end on a Saturday)."""
        return int((self.data_date - self.origin).days)


def hub_weeks(data_date: pd.Timestamp, horizons: tuple[int, ...] = HUB_HORIZONS) -> HubWeeks:
    """Nowcast and forecast weeks of the round whose data end on ``data_date``."""
    d = pd.Timestamp(data_date).normalize()
    origin, ref = last_saturday(d), reference_date(d)
    weeks = []
    for h in horizons:
        end = ref + pd.Timedelta(days=DAYS_PER_WEEK * h)
        step = int((end - origin).days // DAYS_PER_WEEK)
        weeks.append(HubWeek(h, end, "nowcast" if step <= 0 else "forecast", step))
    return HubWeeks(d, origin, ref, tuple(weeks))


# --------------------------------------------------------------------------------- mixing


def mix_quantiles(quantiles: NDArray[np.float64], levels: NDArray[np.float64],
                  n_levels: int = MIX_LEVELS) -> NDArray[np.float64]:
    """The equal mixture of K forecasts ``(K, ..., Q)`` as quantiles ``(..., Q)``: stratified
    draws of each component's quantile function, pooled."""
    u = (np.arange(n_levels) + 0.5) / n_levels
    draws = quantiles_at(levels, quantiles, np.broadcast_to(u, quantiles.shape[:-1]
                                                            + (n_levels,)))     # (K, ..., M)
    pooled = np.moveaxis(draws, 0, -2).reshape(*quantiles.shape[1:-1], -1)
    return quantiles_from_samples(pooled, levels)


def week_sums(histories: CompletedHistories, ends: Sequence[pd.Timestamp]
              ) -> NDArray[np.float64]:
    """``(K, W)`` cases of the 7-day weeks ending on ``ends`` in every completion."""
    positions = histories.dates.get_indexer(pd.DatetimeIndex(list(ends)))
    if (positions < DAYS_PER_WEEK - 1).any():
        raise TargetError(f"weeks ending {list(ends)} are not all in the history")
    cumulative = np.concatenate([np.zeros((len(histories), 1)),
                                 np.cumsum(histories.cases, axis=1)], axis=1)
    return np.asarray(cumulative[:, positions + 1] - cumulative[:, positions + 1 - DAYS_PER_WEEK],
                      dtype=np.float64)


def day_index(dates: pd.DatetimeIndex, date: pd.Timestamp) -> int:
    """The position of ``date`` in ``dates`` (an error naming it when absent)."""
    pos = int(dates.get_indexer(pd.DatetimeIndex([pd.Timestamp(date)]))[0])
    if pos < 0:
        raise TargetError(f"{pd.Timestamp(date).date()} is not a day of the history "
                          f"({dates[0].date()} … {dates[-1].date()})")
    return pos


def weekday_shares(histories: CompletedHistories, until: pd.Timestamp,
                   weeks: int = WEEKDAY_SHARE_WEEKS) -> NDArray[np.float64]:
    """``(K, 7)`` share of a week's cases on each weekday (Monday = 0) over the ``weeks`` weeks
    ending on ``until``."""
    end = day_index(histories.dates, until) + 1
    start = max(end - weeks * DAYS_PER_WEEK, 0)
    cases = histories.cases[:, start:end].astype(np.float64) + 0.5
    weekday = histories.dates[start:end].weekday.to_numpy()
    totals = np.stack([cases[:, weekday == w].sum(axis=1) for w in range(DAYS_PER_WEEK)], axis=1)
    return totals / totals.sum(axis=1, keepdims=True)


# ------------------------------------------------------------------------------ the forecast


@dataclass(frozen=True, eq=False)
class NowcastForecast:
    """Quantiles ``(H, Q)`` of weekly cases at the hub weeks ``weeks`` (nowcast or forecast),
    per completion ``(K, H, Q)`` too (hub files' sample paths and diagnostics)."""

    weeks: HubWeeks
    levels: NDArray[np.float64]
    quantiles: NDArray[np.float64]
    per_completion: NDArray[np.float64]
    forecaster: str


def nowcast_then_forecast(histories: CompletedHistories, data_date: pd.Timestamp,
                          forecaster: CompletionForecaster,
                          levels: NDArray[np.float64], seed: int, *,
                          horizons: tuple[int, ...] = HUB_HORIZONS,
                          partial_week: bool = False) -> NowcastForecast:
    """Every completion forecast from the last Saturday ≤ ``data_date`` (one batch), nowcast
    weeks from the completions' own counts, mixed (module docstring)."""
    return nowcast_then_forecast_places({None: histories}, data_date, forecaster, levels, seed,
                                        horizons=horizons, partial_week=partial_week)[None]


def nowcast_then_forecast_places(completed: Mapping[Place, CompletedHistories],
                                 data_date: pd.Timestamp,
                                 forecaster: CompletionForecaster,
                                 levels: NDArray[np.float64], seed: int, *,
                                 horizons: tuple[int, ...] = HUB_HORIZONS,
                                 partial_week: bool = False
                                 ) -> dict[Place, NowcastForecast]:
    """:func:`nowcast_then_forecast` of every place's completions, all in one forecaster call.
    A :class:`MemberwiseForecaster`'s members are each mixed over the completions, then
    combined (the weekly run's order); any other forecaster is mixed as it comes."""
    weeks = hub_weeks(data_date, horizons)
    for place, histories in completed.items():
        if histories.dates[-1] != weeks.data_date:
            raise TargetError(f"{place or 'the'} completed histories end "
                              f"{histories.dates[-1].date()}, the data date is "
                              f"{weeks.data_date.date()}")
    steps = weeks.forecast_steps
    forecast_at = [weeks.weeks.index(w) for w in weeks.weeks if w.kind == "forecast"]
    places = [p for p, h in completed.items() for _ in range(len(h))]
    cells = [h for c in completed.values() for h in c.histories(up_to=weeks.origin)]
    bounds = np.cumsum([0] + [len(c) for c in completed.values()])
    members = np.empty((1, len(cells), 0, len(levels)))                              # (M, B, H, Q)
    if steps and isinstance(forecaster, MemberwiseForecaster):
        members = forecaster.member_quantiles(cells, steps, levels, seed, places)
    elif steps:
        members = forecaster(cells, steps, levels, seed, places)[None]
    out: dict[Place, NowcastForecast] = {}
    for i, (place, histories) in enumerate(completed.items()):
        per = _nowcast_weeks(histories, weeks, len(levels))                          # (K, W, Q)
        mixed: NDArray[np.float64] | None = None
        if steps:
            own = np.stack([_with_known_days(m[bounds[i]:bounds[i + 1]], histories, weeks,
                                             partial_week) for m in members])   # (M, K, H, Q)
            if isinstance(forecaster, MemberwiseForecaster):
                per[:, forecast_at] = forecaster.combine(own)
                mixed = forecaster.combine(np.stack([mix_quantiles(m, levels) for m in own]))
            else:
                per[:, forecast_at] = own[0]
        quantiles = mix_quantiles(per, levels)
        if mixed is not None:
            quantiles[forecast_at] = mixed
        out[place] = NowcastForecast(weeks, np.asarray(levels, dtype=np.float64), quantiles,
                                     per, forecaster.name)
    return out


def _nowcast_weeks(histories: CompletedHistories, weeks: HubWeeks, n_levels: int
                   ) -> NDArray[np.float64]:
    """``(K, W, Q)``: each completion's count of every nowcast week (a point per completion),
    NaN at the forecast weeks."""
    per = np.full((len(histories), len(weeks.weeks), n_levels), np.nan)
    nowcast_weeks = [w for w in weeks.weeks if w.kind == "nowcast"]
    if nowcast_weeks:
        sums = week_sums(histories, [w.end for w in nowcast_weeks])                # (K, W)
        for j, w in enumerate(nowcast_weeks):
            per[:, weeks.weeks.index(w)] = sums[:, j, None]
    return per


def _with_known_days(forecast: NDArray[np.float64], histories: CompletedHistories,
                     weeks: HubWeeks, partial_week: bool) -> NDArray[np.float64]:
    """The current week (step 1) as its known days' nowcast plus the forecast of the rest
    (``partial_week``), else the forecast's week floored at its known days."""
    known = weeks.known_days_after_origin
    if not partial_week or known == 0 or 1 not in weeks.forecast_steps:
        return floor_current_week(forecast, histories, weeks.origin, weeks.forecast_steps)
    shares = weekday_shares(histories, weeks.origin)                            # (K, 7)
    days = (weeks.origin + pd.Timedelta(days=d) for d in range(1, known + 1))
    weekday = np.array([d.weekday() for d in days])
    rest = 1.0 - shares[:, weekday].sum(axis=1)                                  # (K,)
    tail = histories.cases[:, -known:].sum(axis=1).astype(np.float64)
    out = forecast.copy()
    j = weeks.forecast_steps.index(1)
    out[:, j] = tail[:, None] + rest[:, None] * forecast[:, j]
    return out


def truncated_forecast(history: EpiHistory, data_date: pd.Timestamp,
                       forecaster: CompletionForecaster, levels: NDArray[np.float64],
                       seed: int, *, drop_days: int,
                       horizons: tuple[int, ...] = HUB_HORIZONS) -> NDArray[np.float64]:
    """Quantiles ``(H, Q)`` at the hub weeks of ``data_date`` without a nowcast: the data
    after ``data_date − drop_days`` are dropped (today's run drops 14), the origin is the last
    Saturday ≤ the last day kept and the forecast runs as many weeks as the hub weeks need; a
    week ending on or before that origin is its count as reported (the truncated data as is)."""
    return truncated_forecasts({None: history}, data_date, forecaster, levels, seed,
                               drop_days=drop_days, horizons=horizons)[None]


def truncated_forecasts(histories: Mapping[Place, EpiHistory], data_date: pd.Timestamp,
                        forecaster: CompletionForecaster, levels: NDArray[np.float64],
                        seed: int, *, drop_days: int, horizons: tuple[int, ...] = HUB_HORIZONS
                        ) -> dict[Place, NDArray[np.float64]]:
    """:func:`truncated_forecast` of every place, one forecaster call per origin (places whose
    data end on the same day share it)."""
    weeks = hub_weeks(data_date, horizons)
    seen = {p: h.up_to(weeks.data_date - pd.Timedelta(days=drop_days))
            for p, h in histories.items()}
    origins = {p: last_saturday(h.origin) for p, h in seen.items()}
    out = {p: np.empty((len(weeks.weeks), len(levels))) for p in histories}
    for origin in dict.fromkeys(origins.values()):
        group = [p for p in histories if origins[p] == origin]
        steps = [int((w.end - origin).days // DAYS_PER_WEEK) for w in weeks.weeks]
        ahead = tuple(s for s in steps if s > 0)
        if ahead:
            forecast = forecaster([seen[p].up_to(origin) for p in group], ahead, levels, seed,
                                  group)
            for b, p in enumerate(group):
                for j, s in enumerate(ahead):
                    out[p][steps.index(s)] = forecast[b, j]
        for p in group:
            for i, s in enumerate(steps):
                if s <= 0:
                    pos = day_index(histories[p].dates, weeks.weeks[i].end)
                    out[p][i] = float(histories[p].cases[pos - DAYS_PER_WEEK + 1:pos + 1].sum())
    return out


# ------------------------------------------------------------------------- the weekly run


@dataclass(frozen=True, eq=False)
class RunNowcast:
    """The weekly run's nowcast: the completions, their per-day median (the history the
    backtest scores against), the round's weeks and where the delay model came from."""

    nowcast: Nowcast
    completed: CompletedHistories
    median_history: EpiHistory
    weeks: HubWeeks
    delay_model: str

    def week_samples(self, end: pd.Timestamp) -> NDArray[np.float64]:
        """``(K,)`` final cases of the 7-day week ending ``end`` in each completion."""
        return week_sums(self.completed, [pd.Timestamp(end)])[:, 0]

    def week_observed(self, end: pd.Timestamp) -> float:
        """The same week's cases as reported so far."""
        observed = self.completed.history(0).cases.astype(np.float64).copy()
        start = day_index(self.completed.dates, self.nowcast.dates[0])
        observed[start:] = self.nowcast.observed
        pos = day_index(self.completed.dates, end)
        return float(observed[pos - DAYS_PER_WEEK + 1:pos + 1].sum())

    def reported_share(self, end: pd.Timestamp) -> NDArray[np.float64]:
        """``(K,)`` share of the week's final cases reported so far."""
        return self.week_observed(end) / np.maximum(self.week_samples(end), 1.0)


def median_history(history: EpiHistory, nowcast: Nowcast) -> EpiHistory:
    """``history`` completed with the per-day median of the nowcast (never below reported)."""
    median = np.maximum(np.rint(np.median(nowcast.samples, axis=0)).astype(np.int64),
                        nowcast.observed)
    point = Nowcast(nowcast.dates, nowcast.observed, median[None, :],
                    nowcast.completeness.mean(axis=0, keepdims=True), nowcast.as_of)
    return complete_histories(history, point).history(0)


@dataclass(frozen=True, eq=False)
class CompletionMixture:
    """A weekly member that, at origins from ``active_from`` on (where the data are still being
    reported), forecasts every completion and publishes their mixture; earlier origins (final
    data) are forecast as they are. At the round's own origin the mixture's current week is
    floored at the cases already reported for its days in the data (:func:`floor_current_week`).
    Sample paths: an equal share of each completion's."""

    member: Member
    completed: CompletedHistories
    active_from: pd.Timestamp
    n_mixed: int = 32                  # the first completions are forecast

    @property
    def name(self) -> str:
        return self.member.name

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        if history.origin < self.active_from:
            return self.member.forecast(history, horizons, levels, seed)
        forecasts = [self.member.forecast(h, horizons, levels, seed)
                     for h in self.completed.histories(up_to=history.origin, count=self.n_mixed)]
        cases = floor_current_week(
            mix_quantiles(np.stack([f.values["cases"] for f in forecasts]), levels),
            self.completed, history.origin, horizons)
        return quantile_forecast_from_weekly_cases(
            self.name, history.origin, tuple(horizons), levels, cases, history.population,
            pooled_paths([f.paths for f in forecasts]))


def floor_current_week(cases: NDArray[np.float64], completed: CompletedHistories,
                       origin: pd.Timestamp, horizons: Sequence[int]) -> NDArray[np.float64]:
    """Quantiles ``(..., H, Q)`` of weekly cases with the week after ``origin`` raised to at
    least the cases already reported for its days in the data.

    Only at the round's own origin — the last Saturday before the data date, whose week is
    partly in the data (1–6 days): a week cannot end below what has been reported in it (the
    hub baseline and the flows forecast from the origin and did not see those days). The floor
    is the reported count, not a completion's nowcast of it: flooring at each completion's own
    count was measured worse (``bench/nowcast.py``, hub horizon 0: 0.629 of drop-14 against
    0.568 unfloored), as the newest days' nowcast is the least certain. An earlier origin (a
    backtest cell) sees nothing after itself, so nothing changes there."""
    known = int((completed.dates[-1] - origin).days)
    if completed.reported is None or not 0 < known < DAYS_PER_WEEK or 1 not in horizons:
        return cases
    reported = float(completed.reported[-known:].sum())
    out = cases.copy()
    j = list(horizons).index(1)
    out[..., j, :] = np.maximum(out[..., j, :], reported)
    return out


def pooled_paths(paths: Sequence[NDArray[np.float64] | None]) -> NDArray[np.float64] | None:
    """An equal share of every completion's sample paths (None when any has none)."""
    if any(p is None for p in paths):
        return None
    arrays = [p for p in paths if p is not None]
    n = min(len(p) for p in arrays)
    per = int(np.ceil(n / len(arrays)))
    return np.concatenate([p[:per] for p in arrays])[:n]
