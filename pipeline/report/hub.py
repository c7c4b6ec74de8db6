"""The report of a hub round (any disease: the COVID-19 hub, FluSight, RSV): national
admissions and the states rising, every location's forecast, and the method's track record over
the earlier rounds.

Page 1 (:class:`~pipeline.report.content.PageOne`): the tile-grid map of the states by the
probability, from the published sample trajectories, that the week two weeks ahead (horizon 1)
exceeds the week just past (horizon −1, nowcast), the US fan chart beside it, the headline, the
national forecast at the hub's horizons (median, 50 % and 95 % intervals) and what the round
left out or held. Then every location as small multiples with its fan and observed weeks, a
table of every location, the ED share the same way, and the track record.

The track record compares like with like (:func:`hub_baseline_as_scored`): every horizon against
the hub's own baseline as the hub scores it — horizons 0 … 3 against the re-implemented baseline
(a member scored beside), horizon −1 against the last value reported in the round's own data, a
point mass (the baseline's flat forecast; its WIS is the absolute error). A round is scored only
against data released after it: the newest round's week −1 is this round's own data, not yet
revised, and scores nothing.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline import __version__
from pipeline.backtest.hub_result import HubRoundsResult
from pipeline.combine.combiner import PUBLISHED
from pipeline.data.hub.locations import BY_LOCATION, US
from pipeline.data.hub.nhsn_vintages import TARGETS
from pipeline.evaluation.quantile_function import level_index, median_index
from pipeline.members.hub_baseline import HUB_BASELINE
from pipeline.panels.hub import is_share, target_scale
from pipeline.panels.panel import weeks_ending
from pipeline.panels.quantiles import Quantiles
from pipeline.report.content import (FigureItem, Notice, NoticeKind, PageOne, Provenance,
                                     ReportContent, Section, TableItem)
from pipeline.report.hub_figures import (relative_wis_by_round_figure, small_multiples_figure,
                                         tile_map_figure)
from pipeline.report.page1 import fan_chart_figure

HISTORY_WEEKS = 12
RISING, FALLING = 0.7, 0.3
BAND_LEVELS = (0.025, 0.25, 0.5, 0.75, 0.975)
HUB_NAMES = {"covid": "CDC COVID-19 Forecast Hub", "flu": "CDC FluSight forecast hub",
             "rsv": "CDC RSV Forecast Hub"}
DISEASE_NAMES = {"covid": "COVID-19", "flu": "influenza", "rsv": "RSV"}


def disease_of(target: str) -> str:
    """The disease a hub target is of (covid, flu, rsv; covid for a target not in the catalogue)."""
    spec = TARGETS.get(target)
    return spec.disease if spec is not None else "covid"


def rising_probability(result: HubRoundsResult, index: int = -1) -> NDArray[np.float64]:
    """P(horizon 1's week > horizon −1's) per location at a round, from the published sample
    trajectories (NaN without samples)."""
    if result.samples is None:
        return np.full(len(result.places), np.nan)
    ahead, now = (result.draws(horizon, index) for horizon in (1, -1))          # (C, n)
    return np.mean(ahead > now, axis=1)


def _band_positions(levels: NDArray[np.float64]) -> list[int]:
    """Where the fans' bands (:data:`BAND_LEVELS`) are among ``levels``."""
    return [level_index(levels, lv) for lv in BAND_LEVELS]


def _fmt(value: float, share: bool) -> str:
    return f"{100 * value:.2f}%" if share else f"{value:,.0f}"


def _interval(q: NDArray[np.float64], levels: NDArray[np.float64], coverage: float,
              share: bool) -> str:
    lo, hi = level_index(levels, (1 - coverage) / 2), level_index(levels, (1 + coverage) / 2)
    return f"{_fmt(q[lo], share)}–{_fmt(q[hi], share)}"


def _horizon_label(h: int) -> str:
    return f"{h:+d} wk".replace("-", "−")


def forecast_table(result: HubRoundsResult, place: str) -> pd.DataFrame:
    """One location's published forecast: a row per hub horizon."""
    levels, share = result.levels, is_share(result.target)
    rnd = result.rounds[-1]
    values = result.quantiles().at(place=place, origin=rnd.reference)         # (H, Q)
    return pd.DataFrame(
        {"week ending": [str(rnd.target_end(h).date()) for h in result.horizons],
         "median": [_fmt(q[median_index(levels)], share) for q in values],
         "50% interval": [_interval(q, levels, 0.5, share) for q in values],
         "95% interval": [_interval(q, levels, 0.95, share) for q in values]},
        index=pd.Index([_horizon_label(h) + (" nowcast" if step <= 0 else "")
                        for h, step in zip(result.horizons, rnd.steps(result.horizons))],
                       name="horizon"))


def locations_table(result: HubRoundsResult) -> pd.DataFrame:
    """Every location: the week just past (nowcast), the median and 95 % interval two weeks
    ahead, and P(rising)."""
    levels, share = result.levels, is_share(result.target)
    published, newest = result.quantiles(), result.references[-1]
    now, ahead = (published.at(origin=newest, horizon=h) for h in (-1, 1))      # (C, Q)
    mid = median_index(levels)
    p = rising_probability(result)
    rows = {BY_LOCATION[place].name if place in BY_LOCATION else place: {
        "nowcast, last week": _fmt(now[c, mid], share),
        "median in 2 weeks": _fmt(ahead[c, mid], share),
        "95% interval": _interval(ahead[c], levels, 0.95, share),
        "P(rising)": "—" if not np.isfinite(p[c]) else f"{p[c]:.0%}"}
        for c, place in enumerate(result.places)}
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("location")


def movers(result: HubRoundsResult) -> tuple[list[tuple[str, float]], list[tuple[str, float]]]:
    """(rising, falling): locations with P(rising) ≥ 0.7 or ≤ 0.3, most certain first."""
    p = rising_probability(result)
    named = [(BY_LOCATION[pl].name if pl in BY_LOCATION else pl, float(pr))
             for pl, pr in zip(result.places, p) if pl != US and np.isfinite(pr)]
    up = sorted([x for x in named if x[1] >= RISING], key=lambda x: -x[1])
    down = sorted([x for x in named if x[1] <= FALLING], key=lambda x: x[1])
    return up, down


def fan_figure(result: HubRoundsResult) -> bytes:
    """Small multiples of every location (the last weeks as reported in the round's vintage)."""
    rnd = result.rounds[-1]
    scale = target_scale(result.target)
    ends = list(pd.date_range(end=rnd.origin, periods=HISTORY_WEEKS, freq="7D"))
    observed = np.stack([weeks_ending(rnd.panel.histories[p], rnd.origin, HISTORY_WEEKS)
                         for p in result.places]) / scale
    bands = result.quantiles().at(origin=rnd.reference)[..., _band_positions(result.levels)]
    names = [BY_LOCATION[p].name if p in BY_LOCATION else p for p in result.places]
    unit = "share of ED visits" if is_share(result.target) else "weekly admissions"
    return small_multiples_figure(names, [e.date() for e in ends], observed,
                                  [rnd.target_end(h).date() for h in result.horizons], bands,
                                  unit=unit)


def last_reported(result: HubRoundsResult) -> NDArray[np.float64]:
    """``(C, R)`` the last value each round's own vintage reported for each location (the
    week ending at the round's origin), in the hub's units."""
    scale = target_scale(result.target)
    return np.array([[weeks_ending(rnd.panel.histories[place], rnd.origin, 1)[0]
                      if place in rnd.panel.histories else np.nan for rnd in result.rounds]
                     for place in result.places], dtype=np.float64) / scale


def hub_baseline_as_scored(result: HubRoundsResult) -> Quantiles:
    """The hub's baseline as the hub scores it (module docstring): the re-implemented baseline
    at horizons 0 … 3 and, at horizon −1, a point mass at the last value reported (every
    quantile that value)."""
    baseline = result.forecasts[HUB_BASELINE]
    values = baseline.values.copy()
    if -1 in result.horizons:
        values[:, :, result.horizon_index(-1), :] = last_reported(result)[..., None]
    return baseline.with_values(values)


def scored_rounds(result: HubRoundsResult) -> NDArray[np.bool_]:
    """``(R,)`` the rounds scored: those made from a vintage older than the truth's (the
    newest round's weeks in the data are the truth itself, not yet revised)."""
    newest = result.rounds[-1].as_of
    return np.array([rnd.as_of < newest for rnd in result.rounds], dtype=bool)


@dataclass(frozen=True, eq=False)
class LikeWithLike:
    """One forecaster's WIS beside the hub's baseline as scored, cell by cell: ``wis`` and
    ``baseline`` ``(C, R, H)`` (NaN where either is not scored), ``covered`` the 50 %/95 %
    coverage ``(C, R, H)`` (NaN where not scored)."""

    wis: NDArray[np.float64]
    baseline: NDArray[np.float64]
    covered50: NDArray[np.float64]
    covered95: NDArray[np.float64]

    def relative(self, axis: tuple[int, ...]) -> NDArray[np.float64]:
        """Σ WIS / Σ WIS of the baseline summed over ``axis`` (NaN where nothing is scored)."""
        num, den = np.nansum(self.wis, axis=axis), np.nansum(self.baseline, axis=axis)
        n = np.isfinite(self.wis).sum(axis=axis)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where((n > 0) & (den > 0), num / np.where(den > 0, den, 1.0), np.nan)


def like_with_like(result: HubRoundsResult, forecaster: str = PUBLISHED) -> LikeWithLike:
    """``forecaster`` and the hub's baseline as scored (:func:`hub_baseline_as_scored`) on the
    same cells of the rounds scored (:func:`scored_rounds`)."""
    truth = result.truth.with_values(
        np.where(scored_rounds(result)[None, :, None], result.truth.values, np.nan))
    mine = result.forecasts[forecaster].score(truth)
    base = hub_baseline_as_scored(result).score(truth).wis
    both = np.isfinite(mine.wis) & np.isfinite(base)

    def only(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.where(both, x, np.nan)
    return LikeWithLike(only(mine.wis), only(base), only(mine.covered[0.5].astype(float)),
                        only(mine.covered[0.95].astype(float)))


def track_record_table(result: HubRoundsResult) -> pd.DataFrame:
    """Every forecaster over the rounds scored: Σ WIS / Σ WIS of the hub's baseline as scored
    per hub horizon (−1 against the last reported value), the 50 %/95 % coverage and the number
    of scored cells (NaN where no week has been scored yet)."""
    rows = {}
    for name in result.forecasts:
        scored = like_with_like(result, name)
        by_horizon = scored.relative((0, 1))
        n = int(np.isfinite(scored.wis).sum())
        row = {f"{h:+d} wk": float(by_horizon[k]) for k, h in enumerate(result.horizons)}
        rows[name] = row | {"50% covered": _mean(scored.covered50),
                            "95% covered": _mean(scored.covered95), "scored": n}
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("forecaster")


def _mean(x: NDArray[np.float64]) -> float:
    return float(np.nanmean(x)) if np.isfinite(x).any() else float("nan")


def track_record_figure(result: HubRoundsResult) -> bytes:
    """The published forecast's relative WIS by round: horizon −1 (against the last reported
    value) and horizons 0 … 3 together."""
    scored = like_with_like(result)
    ahead = [k for k, x in enumerate(result.horizons) if x >= 0]
    nowcast = [result.horizon_index(-1)]
    series = {"horizon −1 (nowcast) vs last reported value":
              LikeWithLike(*(a[:, :, nowcast] for a in _parts(scored))).relative((0, 2)),
              "horizons 0 … 3 vs hub baseline":
              LikeWithLike(*(a[:, :, ahead] for a in _parts(scored))).relative((0, 2))}
    return relative_wis_by_round_figure([r.reference.date() for r in result.rounds], series)


def _parts(x: LikeWithLike) -> tuple[NDArray[np.float64], ...]:
    return x.wis, x.baseline, x.covered50, x.covered95


# ----------------------------------------------------------------------------- page 1

def us_fan_figure(result: HubRoundsResult, *, width_in: float = 3.7) -> bytes:
    """The US forecast over its last observed weeks, the weeks still being reported as a
    nowcast."""
    rnd = result.rounds[-1]
    scale = target_scale(result.target)
    ends = [e.date() for e in pd.date_range(end=rnd.origin, periods=HISTORY_WEEKS, freq="7D")]
    observed = weeks_ending(rnd.panel.histories[US], rnd.origin, HISTORY_WEEKS) / scale
    steps = np.array(rnd.steps(result.horizons))
    targets = [rnd.target_end(h).date() for h in result.horizons]
    bands = result.quantiles().at(place=US, origin=rnd.reference)[:, _band_positions(
        result.levels)]
    nowcast_ends = {t for t, s in zip(targets, steps) if s <= 0}
    unit = "share of ED visits" if is_share(result.target) else "weekly admissions"
    if is_share(result.target):
        observed, bands = 100 * observed, 100 * bands
        unit = "ED visits, %"
    return fan_chart_figure(ends, observed, targets, bands, nowcast=steps <= 0, unit=unit,
                            wide="95%", incomplete=np.array([e in nowcast_ends for e in ends]),
                            title="United States", width_in=width_in, height_in=3.0)


def _headline(result: HubRoundsResult, disease: str) -> str:
    up, down = movers(result)
    levels, rnd = result.levels, result.rounds[-1]
    us = result.quantiles().at(place=US, origin=rnd.reference)                # (H, Q)
    share = is_share(result.target)
    what = "ED-visit share" if share else f"{DISEASE_NAMES[disease]} hospital admissions"
    ahead, now = (us[result.horizon_index(h)] for h in (1, -1))
    mid = median_index(levels)
    return (f"US weekly {what} are forecast at {_fmt(ahead[mid], share)} "
            f"(95%: {_interval(ahead, levels, 0.95, share)}) in the week ending "
            f"{rnd.target_end(1).date()}, against a nowcast of "
            f"{_fmt(now[mid], share)} for the week ending "
            f"{rnd.target_end(-1).date()}. {len(up)} of {len(result.places) - 1} states and "
            f"territories are likely rising (P ≥ {RISING:.0%}), {len(down)} likely falling.")


# Page 1 names at most this many left-out locations a target; beyond that it counts them and
# the appendix names them (a round after a wide outage would otherwise spend page 1's word
# budget on a list of names).
PAGE_ONE_NAMED = 6


def missing_locations(results: Mapping[str, HubRoundsResult],
                      skipped: Mapping[str, Mapping[str, str]]) -> dict[str, list[str]]:
    """Each target's hub locations the round has no forecast of: absent from its data, or
    skipped by the gate (``skipped``)."""
    missing: dict[str, list[str]] = {}
    for target, result in results.items():
        left = [p for p in BY_LOCATION if p not in result.places]
        left += [p for p in skipped.get(target, {}) if p not in left and p not in result.places]
        if left:
            missing[target] = left
    return missing


def round_notices(missing: Mapping[str, Sequence[str]], warnings: Sequence[str]
                  ) -> tuple[Notice, ...]:
    """What the round left out or held: each target's hub locations it has no forecast of
    (``missing``, :func:`missing_locations`: named, or counted when more than
    :data:`PAGE_ONE_NAMED`; the appendix names all and says why) and the data's notes (a stale
    cache, a vintage held for review)."""
    left = []
    for target, places in missing.items():
        if len(places) > PAGE_ONE_NAMED:
            what = f"{len(places)} of {len(BY_LOCATION)} locations, named in the appendix"
        else:
            what = ", ".join(BY_LOCATION[p].name if p in BY_LOCATION else p for p in places)
        left.append(Notice(NoticeKind.LEFT_OUT, f"{_target_label(target)}: {what} "
                           "(no usable data)."))
    return tuple(left) + tuple(Notice(NoticeKind.HELD, w) for w in warnings if w.strip())


def _target_label(target: str) -> str:
    return "ED-visit share" if is_share(target) else "admissions"


def hub_page_one(main: HubRoundsResult, notices: Sequence[Notice]) -> PageOne:
    """Page 1 of a round: the map and the US fan, the headline, the US table, the notices."""
    disease = disease_of(main.target)
    p = rising_probability(main)
    states = [(BY_LOCATION[pl].abbreviation, pr) for pl, pr in zip(main.places, p) if pl != US
              and pl in BY_LOCATION]
    figures = (
        FigureItem(tile_map_figure([a for a, _ in states], np.array([x for _, x in states])),
                   "P(rising), %, by state: horizon 1 above last week's nowcast.",
                   "Tile map of the states coloured by the probability that admissions rise, "
                   "each tile labelled with its percentage", width="half"),
        FigureItem(us_fan_figure(main), "The US: nowcast and forecast.",
                   "US weekly admissions: observed weeks, the nowcast and the forecast fan",
                   width="half"))
    table = TableItem(forecast_table(main, US), "", css="headline")
    return PageOne(figures, _headline(main, disease), table, tuple(notices))


def hub_report_content(results: Mapping[str, HubRoundsResult], *, reference_date: dt.date,
                       model_id: str, data_vintage: str, warnings: Sequence[str],
                       skipped: Mapping[str, Mapping[str, str]], config: Mapping[str, object],
                       notices: Sequence[Notice] = ()) -> ReportContent:
    """The round's report (module docstring). ``notices``: what else the round left out or
    held, for page 1, beside the locations left out and the data's ``warnings``."""
    counts = [r for t, r in results.items() if not is_share(t)]
    main = counts[0] if counts else next(iter(results.values()))
    disease = disease_of(main.target)
    up, down = movers(main)
    listed = ", ".join(f"{n} {p:.0%}" for n, p in up[:12]) or "none"
    lead = (f"{len(up)} of {len(main.places) - 1} states and territories likely rising (P ≥ 70 % "
            f"that admissions two weeks ahead exceed last week's): {listed}. "
            f"{len(down)} likely falling.")
    missing = missing_locations(results, skipped)
    page1 = hub_page_one(main, round_notices(missing, warnings) + tuple(notices))
    sections: list[Section] = []
    for target, result in results.items():
        label = "ED-visit share" if is_share(target) else "hospital admissions"
        sections.append(Section(f"locations-{label.split()[0].lower()}",
                                f"Every location: weekly {label}", (
            FigureItem(fan_figure(result), (
                f"Weekly {label} of every location: the last {HISTORY_WEEKS} weeks as "
                "reported in this round's data (black; the last still being reported) and the "
                "published forecast (median, 50 % and 95 % intervals) for the hub's horizons "
                "−1 … 3. Each panel has its own scale."), f"Small multiples of {label}"),
            TableItem(locations_table(result), (
                "Every location: last week's nowcast, the median and 95 % interval two weeks "
                "ahead, and the probability that the week two weeks ahead exceeds last week "
                "(from the published sample trajectories)."))), new_page=bool(sections)))
        scored = scored_rounds(result)
        sections.append(Section(f"track-{label.split()[0].lower()}",
                                 f"Track record: {label}", (TableItem(
            track_record_table(result), (
                f"Every forecaster over the {int(scored.sum())} rounds scored of "
                f"{len(result.rounds)} ({result.rounds[0].reference.date()} … "
                f"{result.rounds[-1].reference.date()}), each made from the data as released by "
                "its due date and scored against this round's data: Σ WIS / Σ WIS of the "
                "hub's baseline as the hub scores it (below 1 beats it) — at horizon −1 the "
                "last value reported in the round's data (a point mass), at 0 … 3 the hub "
                "baseline's forecast — and the share of the scored weeks inside the 50 % and "
                "95 % intervals. The newest round's week −1 is this round's own data, not yet "
                "revised, and is not scored. At −1 every forecaster is the round's nowcast of "
                "the week, so the column is the nowcast's."), decimals=3),
            FigureItem(track_record_figure(result), (
                "The published forecast's relative WIS by round (log scale): horizon −1 "
                "against the last value reported, horizons 0 … 3 against the hub baseline; "
                "below the dashed line beats the baseline."),
                "Relative WIS of the published forecast by round")), new_page=True))
    notes = [f"{t}: {', '.join(f'{p} ({why})' for p, why in s.items())}"
             for t, s in skipped.items() if s]
    # every location without a forecast, those the data never held included (page 1 may only
    # count them)
    every = [f"{t}: " + ", ".join(f"{p} ({skipped.get(t, {}).get(p, 'not in the data')})"
                                  for p in places)
             for t, places in missing.items()]
    provenance = Provenance(package_version=__version__, config=dict(config),
                            extra={"model": model_id, "data": data_vintage,
                                   "locations left out": "; ".join(every) or "none"})
    return ReportContent(title=f"{HUB_NAMES[disease]} round {reference_date} — {model_id}",
                         reference_date=reference_date, data_vintage=data_vintage,
                         sections=tuple(sections), provenance=provenance,
                         warnings=tuple(warnings) + tuple(f"Left out: {n}" for n in notes),
                         summary=lead, headline=None, page1=page1,
                         kicker="flowcast forecast hub round")
