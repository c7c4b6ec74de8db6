"""The report of a hub round: national admissions and the states rising, every location's
forecast, and the method's track record over the earlier rounds.

Page 1 (the headline): the national forecast of weekly admissions at the hub's horizons (median,
50 % and 95 % intervals) and the locations whose admissions are likely rising or falling — the
probability, from the published sample trajectories, that the week two weeks ahead (horizon 1)
exceeds the week just past (horizon −1, nowcast). Then every location as small multiples with
its fan and observed weeks, a table of every location, the ED share the same way, and the track
record: each forecaster's WIS relative to the hub baseline (the re-implemented one, a member
scored beside) per horizon over the earlier rounds, and the intervals' coverage.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline import __version__
from pipeline.backtest.hub_rounds import HubRoundsResult
from pipeline.combine.combiner import PUBLISHED
from pipeline.data.hub.locations import BY_LOCATION, US
from pipeline.panels.hub import is_share, target_scale
from pipeline.panels.panel import weeks_ending
from pipeline.report.content import (FigureItem, Provenance, ReportContent, Section, TableItem)
from pipeline.report.hub_figures import small_multiples_figure

HISTORY_WEEKS = 12
RISING, FALLING = 0.7, 0.3
BAND_LEVELS = (0.025, 0.25, 0.5, 0.75, 0.975)


def _at(levels: NDArray[np.float64], level: float) -> int:
    return int(np.argmin(np.abs(levels - level)))


def rising_probability(result: HubRoundsResult, index: int = -1) -> NDArray[np.float64]:
    """P(horizon 1's week > horizon −1's) per location at a round, from the published sample
    trajectories (NaN without samples)."""
    if result.samples is None:
        return np.full(len(result.places), np.nan)
    h = list(result.horizons)
    draws = result.samples[:, index]                                          # (C, n, H)
    return np.mean(draws[:, :, h.index(1)] > draws[:, :, h.index(-1)], axis=1)


def _fmt(value: float, share: bool) -> str:
    return f"{100 * value:.2f}%" if share else f"{value:,.0f}"


def _interval(q: NDArray[np.float64], levels: NDArray[np.float64], coverage: float,
              share: bool) -> str:
    lo, hi = (1 - coverage) / 2, 1 - (1 - coverage) / 2
    return f"{_fmt(q[_at(levels, lo)], share)} – {_fmt(q[_at(levels, hi)], share)}"


def forecast_table(result: HubRoundsResult, place: str) -> pd.DataFrame:
    """One location's published forecast: a row per hub horizon."""
    levels, share = result.levels, is_share(result.target)
    c = result.places.index(place)
    rnd = result.rounds[-1]
    values = result.forecasts[PUBLISHED][c, -1]
    return pd.DataFrame(
        {"week ending": [str(rnd.target_end(h).date()) for h in result.horizons],
         "median": [_fmt(q[_at(levels, 0.5)], share) for q in values],
         "50% interval": [_interval(q, levels, 0.5, share) for q in values],
         "95% interval": [_interval(q, levels, 0.95, share) for q in values]},
        index=pd.Index([f"{h:+d} wk" for h in result.horizons], name="horizon"))


def locations_table(result: HubRoundsResult) -> pd.DataFrame:
    """Every location: the week just past (nowcast), the median and 95 % interval two weeks
    ahead, and P(rising)."""
    levels, share = result.levels, is_share(result.target)
    h = list(result.horizons)
    values = result.forecasts[PUBLISHED][:, -1]
    p = rising_probability(result)
    rows = {BY_LOCATION[place].name if place in BY_LOCATION else place: {
        "nowcast, last week": _fmt(values[c, h.index(-1), _at(levels, 0.5)], share),
        "median in 2 weeks": _fmt(values[c, h.index(1), _at(levels, 0.5)], share),
        "95% interval": _interval(values[c, h.index(1)], levels, 0.95, share),
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
    levels = result.levels
    bands = result.forecasts[PUBLISHED][:, -1][..., [_at(levels, lv) for lv in BAND_LEVELS]]
    names = [BY_LOCATION[p].name if p in BY_LOCATION else p for p in result.places]
    unit = "share of ED visits" if is_share(result.target) else "weekly admissions"
    return small_multiples_figure(names, [e.date() for e in ends], observed,
                                  [rnd.target_end(h).date() for h in result.horizons], bands,
                                  unit=unit)


def track_record_table(result: HubRoundsResult) -> pd.DataFrame:
    """Every forecaster over the earlier rounds: Σ WIS / Σ WIS of the hub baseline per hub
    horizon and overall, and the 50 %/95 % coverage (NaN where no week has ended yet)."""
    rows = {}
    for name in result.forecasts:
        s = result.summary(name)
        ratios = s["relative_wis_vs_baseline"]
        row = {f"{h:+d} wk": _or_nan(ratios[f"h{h}"]) for h in result.horizons}
        rows[name] = row | {"50% covered": _or_nan(s.get("coverage50")),
                            "95% covered": _or_nan(s.get("coverage95")),
                            "scored": float(s["n_scored"])}
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("forecaster")


def _or_nan(value: float | None) -> float:
    return float("nan") if value is None else float(value)


def hub_report_content(results: Mapping[str, HubRoundsResult], *, reference_date: dt.date,
                       model_id: str, data_vintage: str, warnings: Sequence[str],
                       skipped: Mapping[str, Mapping[str, str]], config: Mapping[str, object],
                       dropped: Sequence[str] = ()) -> ReportContent:
    """The round's report (module docstring). ``dropped``: what the round left out of its
    submission (a target, a member) or replaced (a refit), in words: page 1 says it."""
    counts = [r for t, r in results.items() if not is_share(t)]
    main = counts[0] if counts else next(iter(results.values()))
    up, down = movers(main)
    listed = ", ".join(f"{n} {p:.0%}" for n, p in up[:12]) or "none"
    lead = (f"{len(up)} of {len(main.places) - 1} states and territories likely rising (P ≥ 70 % "
            f"that admissions two weeks ahead exceed last week's): {listed}. "
            f"{len(down)} likely falling.")
    headline = Section("headline", f"National weekly COVID-19 hospital admissions, round of "
                       f"{reference_date}", (TableItem(forecast_table(main, US), (
                           "The US forecast at the hub's horizons: horizon −1 is the week just "
                           "past (still being reported: nowcast), 0 the current week, 1–3 the "
                           "next three."), css="headline"),), intro=lead, new_page=False)
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
                "(from the published sample trajectories).")))))
        sections.append(Section(f"track-{label.split()[0].lower()}",
                                 f"Track record: {label}", (TableItem(
            track_record_table(result), (
                f"Every forecaster over the {len(result.rounds)} rounds "
                f"{result.rounds[0].reference.date()} … {result.rounds[-1].reference.date()}, "
                "each made from the data as released by its due date: Σ WIS / Σ WIS of the "
                "hub baseline per horizon (below 1 beats it) and the share of the scored "
                "weeks inside the 50 % and 95 % intervals; scored against this round's "
                "data."), decimals=3),), new_page=True))
    notes = [f"{t}: {', '.join(f'{p} ({why})' for p, why in s.items())}"
             for t, s in skipped.items() if s]
    provenance = Provenance(package_version=__version__, config=dict(config),
                            extra={"model": model_id, "data": data_vintage,
                                   "locations left out": "; ".join(notes) or "none"})
    return ReportContent(title=f"CDC COVID-19 Forecast Hub round {reference_date} — {model_id}",
                         reference_date=reference_date, data_vintage=data_vintage,
                         sections=tuple(sections), provenance=provenance,
                         # issue 37: the degraded round's notice, first on page 1 (a target
                         # missing from the submission must be seen); page 1's design may move it
                         warnings=tuple(f"Not in this submission as planned: {line}"
                                        for line in dropped)
                         + tuple(warnings) + tuple(f"Left out: {n}" for n in notes),
                         summary=lead, headline=headline,
                         kicker="flowcast forecast hub round")
