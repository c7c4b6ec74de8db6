"""FluSight's derived targets of every round of a weekly-admissions backtest
(:class:`~pipeline.backtest.hub_result.HubRoundsResult`): the rate-change pmf and the peak,
each from the round's joint sample paths and its vintage (:mod:`pipeline.outputs.derived_
targets`), beside a climatology of the earlier seasons in the same vintage (real time), with
what was observed in the latest vintage; and a round's rows of them in the hubverse format.

The climatologies: of the rate change, each horizon's category frequencies over every
location and week of the earlier complete seasons (one pseudo-count per category); of the
peak, the earlier seasons' peaks per 100,000 people of every location scaled to the
location's population, and their weeks.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.backtest.hub_result import HubRoundsResult
from pipeline.outputs.derived_targets import (PER, RATE_CHANGE_CATEGORIES, SEASON_WEEKS,
                                              SeasonTails, category_edges, categorize,
                                              observed_peak, observed_rate_change,
                                              peak_draws, peak_week_pmf, rate_change_pmf,
                                              rate_change_rule, season_tails, season_weeks)
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.panel import Panel
from pipeline.panels.quantiles import long_frame
from pipeline.panels.targets import format_level

DERIVED_COLUMNS = ("reference_date", "target", "horizon", "location", "target_end_date",
                   "output_type", "output_type_id", "value")

RATE_HORIZONS: tuple[int, ...] = (0, 1, 2, 3)
RATE_CHANGE = "wk flu hosp rate change"
PEAK = "peak inc flu hosp"
PEAK_WEEK = "peak week inc flu hosp"


@dataclass(frozen=True, eq=False)
class DerivedTargets:
    """Per location × round: ``rate`` ``(C, R, 4, 5)`` pmfs at horizons 0 … 3 and their
    ``rate_observed`` ``(C, R, 4)`` categories (-1 unknown); ``peak`` ``(C, R, Q)`` quantiles
    at ``levels``, ``peak_week`` ``(C, R, W)`` pmfs over each round's season weeks, the
    ``peak_observed`` ``(C, R)`` count and ``peak_week_observed`` index; the ``*_climatology``
    forecasts beside them; ``seasons``: each round's season weeks."""

    places: tuple[str, ...]
    references: tuple[pd.Timestamp, ...]
    levels: NDArray[np.float64]
    rate: NDArray[np.float64]
    rate_climatology: NDArray[np.float64]
    rate_observed: NDArray[np.int64]
    peak: NDArray[np.float64]
    peak_climatology: NDArray[np.float64]
    peak_observed: NDArray[np.float64]
    peak_week: NDArray[np.float64]
    peak_week_climatology: NDArray[np.float64]
    peak_week_observed: NDArray[np.int64]
    seasons: tuple[pd.DatetimeIndex, ...]


def _series(panel: Panel, places: Sequence[str]) -> dict[str, pd.Series]:
    """Each place's weekly counts indexed by the Saturday ending the week."""
    out = {}
    for place in places:
        history = panel.histories.get(place)
        if isinstance(history, WeeklyHistory):
            out[place] = pd.Series(history.cases, index=history.dates)
    return out


def _rate_climatology(history: Mapping[str, pd.Series], population: Mapping[str, float],
                      before: pd.Timestamp) -> NDArray[np.float64]:
    """``(4, 5)`` each horizon's category frequencies over the earlier seasons' weeks."""
    counts = np.ones((len(RATE_HORIZONS), len(RATE_CHANGE_CATEGORIES)))
    rule = rate_change_rule(before)
    for place, series in history.items():
        values = series.to_numpy(dtype=np.float64)
        dates = series.index
        in_season = np.zeros(len(values), dtype=bool)
        for start in range(dates[0].year - 1, before.year + 1):
            days = season_weeks(pd.Timestamp(start, 12, 1))
            if days[-1] < before:
                in_season |= dates.isin(days)
        for k, h in enumerate(RATE_HORIZONS):
            step = h + 1                      # horizon −1 is the base: h + 1 weeks later
            base, later = values[:-step], values[step:]
            keep = in_season[step:] & np.isfinite(base) & np.isfinite(later)
            edges = category_edges(base[keep], np.full(keep.sum(), population[place]), h, rule)
            cats = categorize(later[keep], edges)
            counts[k] += np.bincount(cats[cats >= 0], minlength=len(RATE_CHANGE_CATEGORIES))
    return counts / counts.sum(axis=1, keepdims=True)


def _week_index(days: pd.DatetimeIndex, ends: Sequence[pd.Timestamp]) -> list[int]:
    """Each end's position among the season's weeks (-1: outside the season)."""
    position = {day: k for k, day in enumerate(days)}
    return [position.get(pd.Timestamp(e), -1) for e in ends]


def derive_targets(result: HubRoundsResult, latest: Panel, population: Mapping[str, float],
                   seed: int = 0) -> DerivedTargets:
    """The derived targets of every round of ``result`` (module docstring)."""
    if result.samples is None:
        raise ValueError(f"{result.target}: the backtest kept no sample paths to derive from")
    rng = np.random.default_rng(seed)
    places, horizons, levels = result.places, result.horizons, result.levels
    pops = np.array([population[p] for p in places], dtype=np.float64)
    n_c, n_r = len(places), len(result.rounds)
    shape = (n_c, n_r)
    rate = np.full((*shape, len(RATE_HORIZONS), len(RATE_CHANGE_CATEGORIES)), np.nan)
    rate_clim, rate_obs = np.full_like(rate, np.nan), np.full((*shape, len(RATE_HORIZONS)), -1)
    peak = np.full((*shape, len(levels)), np.nan)
    peak_clim = np.full_like(peak, np.nan)
    week = np.full((*shape, SEASON_WEEKS), np.nan)
    week_clim = np.full_like(week, np.nan)
    peak_obs, week_obs = np.full(shape, np.nan), np.full(shape, -1)
    truth_series = _series(latest, places)
    seasons = []
    for r, rnd in enumerate(result.rounds):
        rule = rate_change_rule(rnd.reference)
        paths = result.samples[:, r]                                          # (C, n, H)
        rate[:, r] = rate_change_pmf(paths, horizons, pops, rule, RATE_HORIZONS)
        rate_obs[:, r] = observed_rate_change(result.truth.values[:, r], horizons, pops, rule,
                                              RATE_HORIZONS)
        vintage = _series(rnd.panel, places)
        rate_clim[:, r] = _rate_climatology(vintage, dict(zip(places, pops)), rnd.reference)
        days = season_weeks(rnd.reference)
        seasons.append(days)
        tails = season_tails(vintage, dict(zip(places, pops)), days[0])
        path_weeks = _week_index(days, [rnd.target_end(h) for h in horizons])
        for c, place in enumerate(places):
            known = vintage[place].reindex(days).to_numpy(dtype=np.float64) \
                if place in vintage else np.full(SEASON_WEEKS, np.nan)
            draws = peak_draws(known, paths[c], path_weeks, tails, pops[c], rng)
            peak[c, r] = np.quantile(draws.intensity, levels)
            week[c, r] = peak_week_pmf(draws.week)
            if tails is not None:
                peak_clim[c, r] = np.quantile(tails.rate[:, 0] * pops[c] / PER, levels)
                week_clim[c, r] = peak_week_pmf(tails.week[:, 0])
            if place in truth_series and truth_series[place].index[-1] >= days[-1]:
                peak_obs[c, r], week_obs[c, r] = observed_peak(
                    truth_series[place].reindex(days).to_numpy(dtype=np.float64))
    return DerivedTargets(places=places, references=result.references, levels=levels,
                          rate=rate, rate_climatology=rate_clim,
                          rate_observed=rate_obs.astype(np.int64), peak=peak,
                          peak_climatology=peak_clim, peak_observed=peak_obs, peak_week=week,
                          peak_week_climatology=week_clim,
                          peak_week_observed=week_obs.astype(np.int64), seasons=tuple(seasons))


def derived_round_frame(targets: DerivedTargets, index: int, peak_weeks: Sequence[str] | None
                        ) -> pd.DataFrame:
    """Round ``index``'s rate-change pmfs (horizons 0 … 3) and, when the hub lists the
    round's season weeks as the peak week's categories (``peak_weeks``), its peak quantiles
    and peak-week pmf, in the hubverse format (horizon and target end date NA for the peak)."""
    reference = targets.references[index]
    ends = {h: str((reference + pd.Timedelta(weeks=h)).date()) for h in RATE_HORIZONS}
    rate = long_frame(targets.rate[:, index], {"location": targets.places,
                                               "horizon": RATE_HORIZONS,
                                               "output_type_id": RATE_CHANGE_CATEGORIES})
    frames = [rate.assign(target=RATE_CHANGE, target_end_date=rate["horizon"].map(ends),
                          output_type="pmf")]
    days = [str(d.date()) for d in targets.seasons[index]]
    if peak_weeks is not None and list(peak_weeks) == days:
        season_wide = {"horizon": None, "target_end_date": None}
        frames += [
            long_frame(targets.peak[:, index], {
                "location": targets.places,
                "output_type_id": [format_level(q) for q in targets.levels]}
            ).assign(target=PEAK, output_type="quantile", **season_wide),
            long_frame(targets.peak_week[:, index], {"location": targets.places,
                                                     "output_type_id": days}
                       ).assign(target=PEAK_WEEK, output_type="pmf", **season_wide)]
    frame = pd.concat(frames, ignore_index=True)
    frame.insert(0, "reference_date", str(reference.date()))
    return frame[list(DERIVED_COLUMNS)]
