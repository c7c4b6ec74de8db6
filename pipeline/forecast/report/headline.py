"""The headline of a weekly run: what page 1 of the report, the Prefect summary artifact and
``reports/index.html`` say first.

Every forecast number is read from the published forecast (``results.weekly.latest``, the same
object the hub submission is written from): medians and the 50 %/90 % interval ends are its
quantiles at the levels 0.5, 0.25/0.75 and 0.05/0.95 — picked, never re-estimated. P(growing)
comes from its sample paths; R_t = β·S/γ is computed per joint sample of the flow's latest forward
estimate; the skill line is the real-time backtest of the same method (relative WIS vs the hub
baseline, coverage), per target and never pooled.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from torch import Tensor

from pipeline.evaluation.quantile_function import CalibrationError, level_index
from pipeline.panels.history import EpiHistory
from pipeline.report.content import ReportError

if TYPE_CHECKING:  # the report must not import torch-heavy modules at run time
    from pipeline.forecast.results import CountySkill, ForecastResults
    from pipeline.backtest.track_record import TrackRecord

PUBLISHED = "published"
TARGET_LABELS = {"cases": "weekly reported cases", "I": "infectious share I"}
# Central intervals of the one convention the report uses: (lower, upper) levels.
INTERVALS = {"50%": (0.25, 0.75), "90%": (0.05, 0.95)}


# ----------------------------------------------------------------------------- formatting

def fmt_count(x: float) -> str:
    """People: a whole number with thousands separators (e.g. 1,234)."""
    return f"{x:,.0f}"


def fmt_share(x: float, digits: int = 2) -> str:
    """A share of the population in percent, 2 significant digits (e.g. 0.081%)."""
    pct = 100.0 * x
    return f"{pct:.1e}%" if 0 < abs(pct) < 1e-3 else f"{pct:.{digits}g}%"


def fmt_prob(p: float) -> str:
    return f"{100.0 * p:.0f}%"


def fmt_rt(x: float) -> str:
    return f"{x:.2f}"


def fmt_range(lo: float, hi: float, fmt: Callable[[float], str] = fmt_count) -> str:
    return f"{fmt(lo)}–{fmt(hi)}"


# ----------------------------------------------------------------------------- numbers

@dataclass(frozen=True)
class Interval:
    """Median and the ends of the 50 % and 90 % central intervals."""

    median: float
    lo50: float
    hi50: float
    lo90: float
    hi90: float

    @classmethod
    def from_quantiles(cls, levels: NDArray[np.float64], values: NDArray[np.float64]
                       ) -> Interval:
        """The published quantiles at 0.5, 0.25/0.75, 0.05/0.95, exactly (no interpolation)."""
        def at(level: float) -> float:
            try:
                return float(values[level_index(levels, level)])
            except CalibrationError as exc:
                raise ReportError(f"the published forecast has no quantile at level {level} "
                                  f"(levels {levels.tolist()})") from exc
        return cls(at(0.5), at(0.25), at(0.75), at(0.05), at(0.95))

    @classmethod
    def from_samples(cls, x: NDArray[np.float64]) -> Interval:
        q = np.quantile(x, [0.5, 0.25, 0.75, 0.05, 0.95])
        return cls(*(float(v) for v in q))

    def scaled(self, factor: float) -> Interval:
        return Interval(*(factor * v for v in asdict(self).values()))


@dataclass(frozen=True)
class HorizonForecast:
    """One forecast week: cases reported that week, I at its end, P(cases above this week's);
    ``kind``: ``current week`` (holds the data date), ``forecast`` (after it)."""

    horizon: int
    target_end: dt.date
    cases: Interval
    infectious: Interval          # I as a share of the population
    p_growing: float              # P(cases that week > cases of the week ending at the origin)
    kind: str = "forecast"


@dataclass(frozen=True)
class NowcastedWeek:
    """A week in the data still being reported: its nowcast (final cases) and how much of it
    had been reported by the data date."""

    target_end: dt.date
    cases: Interval
    reported: float               # cases reported so far
    reported_share: Interval      # reported / final, over the nowcast's samples
    hub_horizon: int

    def text(self) -> str:
        return (f"{fmt_count(self.cases.median)} cases (50%: "
                f"{fmt_range(self.cases.lo50, self.cases.hi50)}; 90%: "
                f"{fmt_range(self.cases.lo90, self.cases.hi90)}) in the week ending "
                f"{self.target_end}, of which {fmt_count(self.reported)} "
                f"({fmt_prob(self.reported_share.median)}, 90%: "
                f"{fmt_range(self.reported_share.lo90, self.reported_share.hi90, fmt_prob)}) "
                "had been reported")


@dataclass(frozen=True)
class Skill:
    """The published forecast's real-time backtest on one target."""

    target: str
    relative_wis: dict[str, float | None]       # h1..h4, all: Σ WIS / Σ WIS(hub baseline)
    coverage50: float | None
    coverage90: float | None
    n_origins: int                               # scored origins
    first_origin: dt.date
    last_origin: dt.date


@dataclass(frozen=True)
class RtEstimate:
    """R_t = β·S/γ per joint sample of the latest forward estimate."""

    date: dt.date
    value: Interval
    n_samples: int
    n_dropped: int                # samples with γ ≤ 0 (or non-finite), left out


@dataclass(frozen=True)
class Headline:
    origin: dt.date               # the Saturday the published forecast is made from
    last_data_day: dt.date
    population: int
    infectious_now: float         # I on the last data day (share)
    origin_week_cases: float      # cases reported in the 7 days ending at the origin
    horizons: tuple[HorizonForecast, ...]
    rt: RtEstimate
    skill: tuple[Skill, ...]
    n_paths: int
    # the NF-seeded SMC forecaster's relative WIS on weekly cases (all horizons), when scored
    smc_relative_wis: float | None = None
    nowcast_weeks: tuple[NowcastedWeek, ...] = ()   # weeks in the data, still being reported
    data_date: dt.date | None = None                 # last day in the data (None: no nowcast)
    # share of each of the last four weeks to the origin already reported (nowcast), newest first
    reported_weeks: tuple[tuple[dt.date, Interval], ...] = ()
    place: str = "San Francisco"                     # the forecast's county

    @property
    def infectious_now_people(self) -> float:
        return self.infectious_now * self.population

    @property
    def p_growing(self) -> float:
        """P(next week's cases > this week's): the first horizon's."""
        return self.horizons[0].p_growing

    def to_dict(self) -> dict[str, object]:
        """JSON-able (dates as ISO strings)."""
        def clean(x: object) -> object:
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [clean(v) for v in x]
            return x.isoformat() if isinstance(x, dt.date) else x
        return {k: clean(v) for k, v in asdict(self).items()} | {"infectious_now_people": self.infectious_now_people,
                                      "text": self.one_line()}

    def nowcast_sentence(self) -> str:
        """The lead's first sentence: the current week (nowcast of its days in the data and
        forecast of the rest) and the nowcast of the week before."""
        if not self.nowcast_weeks or self.data_date is None:
            return ""
        current = next((f for f in self.horizons if f.kind == "current week"), None)
        parts = []
        if current is not None:
            days = (self.data_date - (current.target_end - dt.timedelta(days=6))).days + 1
            parts.append(f"Nowcast of the current week (ending {current.target_end}; data to "
                         f"{self.data_date}, {days} of its 7 days, the rest forecast): "
                         f"{fmt_count(current.cases.median)} cases (50%: "
                         f"{fmt_range(current.cases.lo50, current.cases.hi50)}; 90%: "
                         f"{fmt_range(current.cases.lo90, current.cases.hi90)}).")
        for week in self.nowcast_weeks:
            parts.append(f"Nowcast: {week.text()}.")
        return " ".join(parts) + " "

    def forecast_clause(self, *, place: bool) -> str:
        """The forecast in words, the lead's and page 1's: the first and last week against the
        week to the origin, the chance of growth, R_t (``place``: naming where)."""
        first, last = self.horizons[0], self.horizons[-1]
        rt = self.rt.value
        where = f" in {self.place}" if place else ""
        return (f"Weekly reported cases{where} are forecast at {fmt_count(first.cases.median)} "
                f"(90%: {fmt_range(first.cases.lo90, first.cases.hi90)}) in the week ending "
                f"{first.target_end} and {fmt_count(last.cases.median)} (90%: "
                f"{fmt_range(last.cases.lo90, last.cases.hi90)}) in the week ending "
                f"{last.target_end}, against {fmt_count(self.origin_week_cases)} in the week "
                f"ending {self.origin}. Probability that cases grow next week: "
                f"{fmt_prob(self.p_growing)}; R_t {fmt_rt(rt.median)} (90%: "
                f"{fmt_range(rt.lo90, rt.hi90, fmt_rt)}).")

    def sentence(self) -> str:
        """The lead an epidemiologist can quote (it opens with the nowcast, when there is one)."""
        return self.nowcast_sentence() + (
            f"About {fmt_count(self.infectious_now_people)} people in {self.place} are "
            f"infectious ({fmt_share(self.infectious_now)} of the population: the cases "
            f"reported in the 7 days to {self.last_data_day}). "
            + self.forecast_clause(place=False))

    def one_line(self) -> str:
        """For the index of past runs."""
        first, last = self.horizons[0], self.horizons[-1]
        return (f"{fmt_count(self.infectious_now_people)} infectious on {self.last_data_day}; "
                f"cases week to {first.target_end}: {fmt_count(first.cases.median)} "
                f"(90% {fmt_range(first.cases.lo90, first.cases.hi90)}), week to "
                f"{last.target_end}: {fmt_count(last.cases.median)} "
                f"(90% {fmt_range(last.cases.lo90, last.cases.hi90)}); "
                f"P(growing) {fmt_prob(self.p_growing)}; R_t {fmt_rt(self.rt.value.median)}")

    def skill_line(self, target: str) -> str:
        s = next(k for k in self.skill if k.target == target)
        rel = " / ".join(_fmt_ratio(s.relative_wis.get(f"h{h.horizon}")) for h in self.horizons)
        return (f"{TARGET_LABELS.get(target, target)}: relative WIS vs the hub baseline {rel} "
                f"at 1–{len(self.horizons)} weeks, {_fmt_ratio(s.relative_wis.get('all'))} "
                f"overall; coverage of the 50% / 90% intervals {_fmt_ratio(s.coverage50, 2)} / "
                f"{_fmt_ratio(s.coverage90, 2)}; {s.n_origins} origins "
                f"{s.first_origin} … {s.last_origin}")


def _fmt_ratio(x: float | None, digits: int = 2) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


# ----------------------------------------------------------------------------- computing

def as_numpy(x: Tensor | NDArray[np.float64]) -> NDArray[np.float64]:
    if isinstance(x, Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def origin_week_cases(weekly: TrackRecord) -> float:
    """Cases reported in the 7 days ending at the origin (the week the forecast saw last)."""
    return float(weekly.history.up_to(weekly.origin).weekly_cases()[-1])


def _horizons(weekly: TrackRecord) -> tuple[HorizonForecast, ...]:
    latest = weekly.latest
    if latest.paths is None:
        raise ReportError("the published forecast has no sample paths (P(growing) needs them)")
    population = float(weekly.history.population)
    this_week = origin_week_cases(weekly)
    last_day = weekly.history.dates[-1]
    out = []
    for k, h in enumerate(latest.horizons):
        # weekly cases of a path = N·I at the week's end (the conversion's window is 7 days)
        path_cases = latest.paths[:, k, 1] * population
        end = latest.origin + pd.Timedelta(days=7 * int(h))
        current = end - pd.Timedelta(days=6) <= last_day <= end
        out.append(HorizonForecast(
            horizon=int(h), target_end=end.date(),
            cases=Interval.from_quantiles(latest.levels, latest.values["cases"][k]),
            infectious=Interval.from_quantiles(latest.levels, latest.values["I"][k]),
            p_growing=float(np.mean(path_cases > this_week)),
            kind="current week" if current else "forecast"))
    return tuple(out)


def _reported_weeks(weekly: TrackRecord, n_weeks: int = 4
                    ) -> tuple[tuple[dt.date, Interval], ...]:
    """How much of each of the last ``n_weeks`` weeks ending at the origin had been reported by
    the data date (reported / the nowcast's final cases), newest first."""
    nowcast = weekly.nowcast
    if nowcast is None:
        return ()
    ends = [weekly.origin - pd.Timedelta(days=7 * k) for k in range(n_weeks)]
    return tuple((end.date(), Interval.from_samples(nowcast.reported_share(end))) for end in ends)


def _nowcast_weeks(weekly: TrackRecord) -> tuple[NowcastedWeek, ...]:
    """The round's weeks wholly in the data (hub horizon −1, and 0 on a Saturday), newest
    first: their nowcast and the share reported."""
    nowcast = weekly.nowcast
    if nowcast is None:
        return ()
    out = []
    for week in sorted(nowcast.weeks.weeks, key=lambda w: -w.horizon):
        if week.kind != "nowcast":
            continue
        out.append(NowcastedWeek(
            target_end=week.end.date(), cases=Interval.from_samples(nowcast.week_samples(week.end)),
            reported=nowcast.week_observed(week.end),
            reported_share=Interval.from_samples(nowcast.reported_share(week.end)),
            hub_horizon=week.horizon))
    return tuple(out)


def _skill(weekly: TrackRecord) -> tuple[Skill, ...]:
    summary = weekly.summary()["by_target"]
    scores = weekly.scores
    out = []
    for target in ("cases", "I"):
        s = summary[target][PUBLISHED]
        origins = pd.to_datetime(scores.loc[(scores["forecaster"] == PUBLISHED)
                                            & (scores["target"] == target), "origin_date"])
        out.append(Skill(target=target, relative_wis=dict(s["relative_wis_vs_baseline"]),
                         coverage50=s["coverage50"], coverage90=s["coverage90"],
                         n_origins=int(origins.nunique()), first_origin=origins.min().date(),
                         last_origin=origins.max().date()))
    return tuple(out)


def rt_samples(samples: Tensor | NDArray[np.float64], names: Sequence[str]) -> tuple[NDArray[np.float64], int]:
    """(R_t = β·S/γ per joint sample with γ > 0, number of samples left out)."""
    x = as_numpy(samples)
    missing = [n for n in ("S", "beta", "gamma") if n not in names]
    if missing:
        raise ReportError(f"the latest forward estimate lacks {missing} (has {list(names)})")
    s, beta, gamma = (x[:, list(names).index(n)] for n in ("S", "beta", "gamma"))
    ok = np.isfinite(s) & np.isfinite(beta) & (gamma > 0)
    if not ok.any():
        raise ReportError("no sample of the latest forward estimate has γ > 0; R_t undefined")
    return beta[ok] * s[ok] / gamma[ok], int((~ok).sum())


def _rt(results: ForecastResults) -> RtEstimate:
    latest = results.latest
    rt, dropped = rt_samples(latest.samples["forward"], latest.names)
    return RtEstimate(date=dt.date.fromisoformat(latest.dates["forward"]),
                      value=Interval.from_samples(rt), n_samples=int(rt.size + dropped),
                      n_dropped=dropped)


def published_weekly(results: ForecastResults) -> TrackRecord:
    if results.weekly is None:
        raise ReportError("the run has no published forecast (results.weekly is None)")
    return results.weekly


SMC_FORECASTER = "nf-smc"


def _smc_relative_wis(weekly: TrackRecord) -> float | None:
    cases = weekly.summary()["by_target"]["cases"]
    return cases[SMC_FORECASTER]["relative_wis_vs_baseline"]["all"] if SMC_FORECASTER in cases \
        else None


def daily_history(weekly: TrackRecord) -> EpiHistory:
    """The place's daily series (the weekly report reads I and daily cases)."""
    history = weekly.history
    if not isinstance(history, EpiHistory):
        raise ReportError(f"the weekly report reads a daily series; {weekly.place} has weekly "
                          "counts only")
    return history


def compute_headline(results: ForecastResults) -> Headline:
    weekly = published_weekly(results)
    history = daily_history(weekly)
    latest = weekly.latest
    return Headline(smc_relative_wis=_smc_relative_wis(weekly),
        origin=weekly.origin.date(), last_data_day=history.dates[-1].date(),
        population=int(history.population), infectious_now=float(history.I[-1]),
        origin_week_cases=origin_week_cases(weekly), horizons=_horizons(weekly),
        rt=_rt(results), skill=_skill(weekly),
        n_paths=0 if latest.paths is None else int(latest.paths.shape[0]),
        nowcast_weeks=_nowcast_weeks(weekly), reported_weeks=_reported_weeks(weekly),
        data_date=None if weekly.nowcast is None else history.dates[-1].date(),
        place=results.config.data.place)


# ----------------------------------------------------------------------------- tables

def _people_share(x: Interval, population: int) -> list[str]:
    """Cells "people (share)" for the median and the two intervals of I."""
    people = x.scaled(population)
    return [f"{fmt_count(people.median)} ({fmt_share(x.median)})",
            f"{fmt_range(people.lo50, people.hi50)} ({fmt_range(x.lo50, x.hi50, _pct)}%)",
            f"{fmt_range(people.lo90, people.hi90)} ({fmt_range(x.lo90, x.hi90, _pct)}%)"]


def _pct(x: float) -> str:
    """A share in percent without the sign (a range carries one % at its end)."""
    return fmt_share(x).removesuffix("%")


def week_label(f: HorizonForecast) -> str:
    """A forecast week's row label: its end, the horizon, and ``current`` for the week holding
    the data date (nowcast weeks are labelled ``nowcast``)."""
    return f"{f.target_end} (+{f.horizon} wk{', current' if f.kind == 'current week' else ''})"


def forecast_frame(h: Headline) -> pd.DataFrame:
    """The page-1 table: rows (quantity, week ending), columns median, 50 % and 90 % interval;
    I in people with its share of the population in brackets."""
    cases, infectious = "weekly reported cases", "infectious people I·N (share of population)"
    rows: list[list[str]] = []
    keys: list[tuple[str, str]] = []
    for w in reversed(h.nowcast_weeks):
        keys.append((cases, f"{w.target_end} (nowcast, {fmt_prob(w.reported_share.median)} in)"))
        rows.append([fmt_count(w.cases.median), fmt_range(w.cases.lo50, w.cases.hi50),
                     fmt_range(w.cases.lo90, w.cases.hi90)])
    for label in (cases, infectious):
        for f in h.horizons:
            keys.append((label, week_label(f)))
            rows.append([fmt_count(f.cases.median), fmt_range(f.cases.lo50, f.cases.hi50),
                         fmt_range(f.cases.lo90, f.cases.hi90)] if label == cases
                        else _people_share(f.infectious, h.population))
    index = pd.MultiIndex.from_tuples(keys, names=["forecast", "week ending"])
    return pd.DataFrame(rows, index=index, columns=["median", "50% interval", "90% interval"])


def facts_frame(h: Headline) -> pd.DataFrame:
    """Key facts under the table: P(growing) per horizon, R_t with its intervals."""
    rt = h.rt.value
    growth = " / ".join(fmt_prob(f.p_growing) for f in h.horizons)
    # infectious now and this week's cases are in the lead sentence just above the table
    facts = {
        "P(growing)": f"{fmt_prob(h.p_growing)} that next week's cases exceed this week's "
                      f"({fmt_count(h.origin_week_cases)}, 7 days to {h.origin}); at "
                      f"1–{len(h.horizons)} weeks: {growth} ({h.n_paths} published sample "
                      "paths)",
        "R_t = β·S/γ": f"{fmt_rt(rt.median)} (50%: {fmt_range(rt.lo50, rt.hi50, fmt_rt)}; "
                       f"90%: {fmt_range(rt.lo90, rt.hi90, fmt_rt)}) on {h.rt.date}, per "
                       f"sample of the joint flow's forward estimate"
                       + (f" ({h.rt.n_dropped} of {h.rt.n_samples} samples with γ ≤ 0 left "
                          "out)" if h.rt.n_dropped else ""),
        "one model": "R_t, β, the rollouts and the NF-seeded SMC come from joint flows trained "
                     "on the multi-wave prior of the published forecast's flow member (γ = 1/7 "
                     "per day, fixed by the 7-day window)"
                     + (f"; the SMC's own four-week forecast scores {_fmt_ratio(h.smc_relative_wis)}"
                        " relative WIS on weekly cases in the backtest and is not averaged in"
                        if h.smc_relative_wis is not None else ""),
    }
    if h.reported_weeks:
        facts["reported so far"] = "; ".join(
            f"week to {end}: {fmt_prob(x.median)} ({fmt_range(x.lo90, x.hi90, fmt_prob)})"
            for end, x in h.reported_weeks) + (
            f" of the nowcast final cases, by {h.data_date} (median, 90% interval)")
    return pd.DataFrame({"value": list(facts.values())},
                        index=pd.Index(list(facts), name="growth"))


def skill_frame(h: Headline, county: CountySkill | None = None) -> pd.DataFrame:
    """The published forecast's backtest: relative WIS per horizon and overall, coverage; with
    ``county``, a last row: the same method on weekly cases across California's counties
    (geometric mean over counties)."""
    columns = [*(f"{f.horizon} wk" for f in h.horizons), "all", "50% cov.", "90% cov."]
    keys = [f"h{f.horizon}" for f in h.horizons] + ["all"]
    rows, labels = [], []
    for s in h.skill:
        rows.append([*(s.relative_wis.get(k) for k in keys), s.coverage50, s.coverage90])
        labels.append(TARGET_LABELS.get(s.target, s.target))
    if county is not None:
        rel = county.relative_wis["cases"]["published"]
        rows.append([*(rel.get(k) for k in keys), *county.coverage["cases"]])
        labels.append(f"weekly cases, {county.n_counties} CA counties")
    frame = pd.DataFrame(rows, columns=columns, dtype=float,
                         index=pd.Index(labels, name="target"))
    frame.columns = pd.MultiIndex.from_tuples(
        [("relative WIS vs hub baseline", c) for c in columns[:-2]]
        + [("coverage", c) for c in columns[-2:]])
    return frame


def markdown(h: Headline, banner: str | None, report_path: str = "") -> str:
    """The Prefect summary artifact: the headline table, the stale-data note once."""
    lines = [f"# {h.place} weekly COVID-19 forecast from {h.origin}", ""]
    if banner:
        lines += [f"> **{banner}**", ""]
    lines += [h.sentence(), "",
              "| week ending | weekly cases (median) | 50% | 90% | I (share, median) | I 90% "
              "| P(cases > week to origin) |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for f in h.horizons:
        lines.append(f"| {f.target_end} | {fmt_count(f.cases.median)} | "
                     f"{fmt_range(f.cases.lo50, f.cases.hi50)} | "
                     f"{fmt_range(f.cases.lo90, f.cases.hi90)} | {fmt_share(f.infectious.median)} "
                     f"| {fmt_range(f.infectious.lo90, f.infectious.hi90, fmt_share)} | "
                     f"{fmt_prob(f.p_growing)} |")
    rt = h.rt.value
    lines += ["", f"**R_t** = β·S/γ on {h.rt.date}: {fmt_rt(rt.median)} "
                  f"(50%: {fmt_range(rt.lo50, rt.hi50, fmt_rt)}, "
                  f"90%: {fmt_range(rt.lo90, rt.hi90, fmt_rt)})", "",
              "**Backtest of the published forecast** (real time):", ""]
    lines += [f"- {h.skill_line(s.target)}" for s in h.skill]
    if report_path:
        lines += ["", f"Report: `{report_path}`"]
    return "\n".join(lines) + "\n"
