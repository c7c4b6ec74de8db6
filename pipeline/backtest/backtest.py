"""The one real-time backtest: every member at every (place, origin) cell of a panel, combined,
scored against the latest data.

For each origin t the cells of every forecast place see only the data as known at t
(:class:`DataAtOrigins`: one vintage cut at each origin, or a vintage per origin, as the hub's
rounds were released); each member forecasts all cells in one batch (its own batching); the
published forecast combines them with weights and recalibration learnt only from forecasts
whose target week had ended by t (:mod:`pipeline.combine.combiner`), beside the variants; every
forecaster is then scored per target × horizon against the latest data (the truth).

The result holds labelled quantiles (places × origins × horizons × levels,
:class:`~pipeline.panels.quantiles.Quantiles`) per target and forecaster; summaries, score
tables and hub-format files come from it (:mod:`pipeline.backtest.result`,
:mod:`pipeline.backtest.writers`). San Francisco's weekly track record, the cross-county design
backtest and the hub rounds of NHSN are all this function on different panels.
"""
from __future__ import annotations

import dataclasses
import functools

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.members.isolation import MemberFailure, guarded_forecast
from pipeline.backtest.config import BacktestConfig
from pipeline.backtest.result import BacktestResult
from pipeline.combine.average import EnsembleError
from pipeline.combine.combiner import (PUBLISHED, RESERVED_NAMES, UNCALIBRATED, CombineConfig,
                                       KnownTruth, combine)
from pipeline.combine.paths import sample_paths
from pipeline.combine.plausibility import PlausibilityConfig, bounded, plausible_bands
from pipeline.evaluation.regimes import growth_regimes
from pipeline.members.base import Member, MemberForecast
from pipeline.members.hub_baseline import HUB_BASELINE, HubBaseline
from pipeline.panels.history import History
from pipeline.panels.hub import is_share
from pipeline.panels.panel import Cells, Panel, observed_truth, origin_seed
from pipeline.panels.quantiles import Quantiles
from pipeline.panels.targets import SHARE
from pipeline.progress import ProgressReporter, SilentProgress, start_phase


class DataAtOrigins(Protocol):
    """The data a backtest may use: the panel as known at its i-th origin, and the latest."""

    @property
    def latest(self) -> Panel: ...

    def known_at(self, index: int, origin: pd.Timestamp) -> Panel: ...


@dataclass(frozen=True, eq=False)
class OneVintage:
    """One vintage of the data, each origin seeing it up to that origin (the counties' CDPH
    download, San Francisco's DataSF series): revisions after an origin are not modelled."""

    latest: Panel

    def known_at(self, index: int, origin: pd.Timestamp) -> Panel:
        return self.latest


@dataclass(frozen=True, eq=False)
class Vintages:
    """The vintage each origin was forecast from (the NHSN release of each hub round; two
    rounds may share an origin when a release brought no new week) and the latest."""

    latest: Panel
    known: Sequence[Panel]

    def known_at(self, index: int, origin: pd.Timestamp) -> Panel:
        panel = self.known[index]
        if panel.last_date > origin:
            raise EnsembleError(f"the vintage of origin {origin.date()} holds data up to "
                                f"{panel.last_date.date()}, after its origin")
        return panel

    def truth_known(self, origins: Sequence[pd.Timestamp], horizons: tuple[int, ...]
                    ) -> KnownTruth:
        """The count target's truth ``(C, O, H)`` as origin j's vintage holds it (the latest
        panel's places; NaN where that vintage has no value): the combiner learns at origin j
        from the outcomes then known, as a forecaster did (NHSN's newest week is revised by a
        median of +7 % after its first release)."""
        places, target = self.latest.places, self.latest.count_target
        origins = list(origins)

        row = {place: c for c, place in enumerate(places)}

        @functools.cache
        def at(j: int) -> NDArray[np.float64]:
            known = observed_truth(self.known[j], origins[:j], horizons)[target]
            held = [c for c, p in enumerate(known.places) if p in row]
            out = np.full((len(places), len(origins), len(horizons)), np.nan)
            out[[row[known.places[c]] for c in held], :j] = known.values[held]
            return out
        return at


def backtest_cells(data: DataAtOrigins, origins: Sequence[pd.Timestamp], seed: int) -> Cells:
    """Every forecast place at every origin, place-major (index c·O + o), each from the data as
    known at its origin (a place missing then is forecast from nothing: it must be there)."""
    places = data.latest.places
    histories: list[History] = []
    panels: list[Panel] = []
    for place in places:
        for i, origin in enumerate(origins):
            panel = data.known_at(i, origin)
            if place not in panel.histories:
                raise EnsembleError(f"{place} has no data as known at {origin.date()}")
            histories.append(panel.histories[place].up_to(origin))
            panels.append(panel)
    return Cells(tuple(histories), tuple(p for p in places for _ in origins), tuple(panels),
                 tuple(origin_seed(seed, o) for _ in places for o in origins))


def run_backtest(data: DataAtOrigins, members: Sequence[Member],
                 origins: Sequence[pd.Timestamp], config: BacktestConfig = BacktestConfig(), *,
                 references: Sequence[Member] = (), reported: Sequence[pd.Timestamp] | None = None,
                 truth_at: KnownTruth | None = None,
                 progress: ProgressReporter | None = None) -> BacktestResult:
    """Every member and reference at every cell, the published combination of the members and
    the variants (module docstring). The hub baseline is scored always: as a member when it is
    one, else as a reference. ``reported``: the origins the result keeps (default: all); the
    earlier ones still teach the combiner (a warm-up, so the forecast at a date does not depend
    on where the report starts)."""
    progress = progress or SilentProgress()
    names = tuple(m.name for m in members)
    if not names or len(set(names)) != len(names) or set(RESERVED_NAMES) & set(names):
        raise EnsembleError(f"members need distinct names other than {RESERVED_NAMES}, got "
                            f"{names}")
    if HUB_BASELINE not in names and not any(r.name == HUB_BASELINE for r in references):
        references = (*references, HubBaseline())
    references = tuple(r for r in references if r.name not in names)
    latest, levels = data.latest, np.asarray(config.levels, dtype=np.float64)
    horizons, origins = tuple(config.horizons), list(origins)
    cells = backtest_cells(data, origins, config.seed)
    # one step a cell a forecaster: the bar's total is every forecast the loop below makes
    start_phase(progress, "forecasts", len(cells) * (len(members) + len(references)))
    shape = (len(latest.places), len(origins))
    seconds: dict[str, float] = {}
    forecasts: dict[str, dict[str, Quantiles]] = {t: {} for t in latest.targets}

    def labelled(values: NDArray[np.float64]) -> Quantiles:
        """Quantiles ``(C, O, H, Q)`` of every cell, with their labels."""
        return Quantiles(values, latest.places, tuple(origins), horizons, levels)
    template: NDArray[np.float64] | None = None
    failures: dict[str, MemberFailure] = {}
    for member in (*members, *references):
        started = time.perf_counter()
        guarded = guarded_forecast(member, cells, horizons, levels, config.member_time_limit_s)
        seconds[member.name] = time.perf_counter() - started
        made = guarded.forecast or MemberForecast(
            np.full((len(cells), len(horizons), len(levels)), np.nan))
        if guarded.failed.any():
            failures[member.name] = MemberFailure(guarded.failed.reshape(shape), guarded.why)
        progress.advance(len(cells), member=member.name)
        for target, values in made.values(cells.histories).items():
            forecasts[target][member.name] = labelled(values.reshape(*shape, *values.shape[1:]))
        if (config.n_paths and template is None and member.name in names
                and made.paths is not None and not guarded.failed.any()):
            kept = made.paths[:, :config.n_paths]
            template = kept.reshape(*shape, *kept.shape[1:])
    started = time.perf_counter()
    truth = observed_truth(latest, origins, horizons)
    regimes = cell_regimes(cells).reshape(shape)
    count = latest.count_target
    baseline = forecasts[count][HUB_BASELINE].values

    dropped = {n: f.cells for n, f in failures.items()}

    bands: dict[PlausibilityConfig, NDArray[np.float64]] = {}

    def held(values: NDArray[np.float64], combiner: CombineConfig) -> NDArray[np.float64]:
        """``values`` within the changes the panel has shown, where ``combiner`` says so and
        the target is a count (a proportion such as the ED share is not bounded: held to its
        falls, the share's 95 % interval covered 0.936 [0.921, 0.946]: bench.nhsn at f3da0a0)."""
        if combiner.bounded is None or is_share(count):
            return values
        if combiner.bounded not in bands:
            bands[combiner.bounded] = plausible_bands(cells, horizons, combiner.bounded
                                                      ).reshape(*shape, len(horizons), 2)
        return bounded(values, bands[combiner.bounded])

    def published_by(chosen: Sequence[str], combiner: CombineConfig) -> NDArray[np.float64]:
        return held(combine({n: forecasts[count][n].values for n in chosen}, baseline,
                            truth[count].values, regimes, levels, horizons, origins, combiner,
                            truth_at=truth_at, dropped=dropped).published, combiner)

    combined = combine({n: forecasts[count][n].values for n in names}, baseline,
                       truth[count].values, regimes, levels, horizons, origins, config.combine,
                       truth_at=truth_at, dropped=dropped)
    combined = dataclasses.replace(combined, published=held(combined.published, config.combine))
    _add(forecasts, PUBLISHED, labelled(combined.published), latest)
    _add(forecasts, UNCALIBRATED, labelled(combined.uncalibrated), latest)
    seconds["combine"] = time.perf_counter() - started
    started = time.perf_counter()
    for variant in config.variants:
        unknown = [n for n in variant.members or () if n not in forecasts[count]]
        if unknown:
            raise EnsembleError(f"variant {variant.name!r} combines {unknown}, which the "
                                f"backtest did not forecast ({sorted(forecasts[count])})")
        _add(forecasts, variant.name,
             labelled(published_by(variant.members or names, variant.combine)), latest)
    seconds["variants"] = time.perf_counter() - started
    paths = (published_paths(cells, combined.published, levels, config.n_paths, template)
             if config.n_paths else None)
    keep = (np.ones(len(origins), dtype=bool) if reported is None
            else np.isin(pd.DatetimeIndex(origins), pd.DatetimeIndex(list(reported))))
    return BacktestResult(panel=latest, origins=tuple(origins), horizons=horizons,
                          levels=levels, members=names,
                          references=tuple(r.name for r in references), forecasts=forecasts,
                          truth=truth, regimes=regimes, weights=combined.weights, paths=paths,
                          reported=keep, seconds=seconds, config=config,
                          failures=failures,
                          bounds=(None if config.combine.bounded is None
                                  else bands.get(config.combine.bounded))).reported_only()


def _add(forecasts: dict[str, dict[str, Quantiles]], name: str, count: Quantiles,
         panel: Panel) -> None:
    """A combined forecast of the count under ``name``, and its I = count / N where the panel
    has I."""
    forecasts[panel.count_target][name] = count
    if SHARE in forecasts:
        forecasts[SHARE][name] = count.with_values(
            count.values / panel.populations[:, None, None, None])


def cell_regimes(cells: Cells) -> NDArray[np.intp]:
    """Each cell's growth regime ``(B,)`` from the last two weekly counts it saw."""
    last_two = np.array([_last_two(h.weekly_cases()) for h in cells.histories])
    return growth_regimes(last_two)


def _last_two(weekly: NDArray[np.float64]) -> tuple[float, float]:
    return (float(weekly[-2]), float(weekly[-1])) if weekly.size >= 2 else (np.nan, np.nan)


def published_paths(cells: Cells, published: NDArray[np.float64], levels: NDArray[np.float64],
                    n_paths: int, template: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """``(C, O, n, H, 3)`` weekly S/I/R sample paths of the published forecast at every cell
    (:mod:`pipeline.combine.paths`), their ranks from ``template`` (C, O, n, H, 3) when given."""
    n_c, n_o, n_h = published.shape[:3]
    out = np.full((n_c, n_o, n_paths, n_h, 3), np.nan)
    for b, history in enumerate(cells.histories):
        c, o = divmod(b, n_o)
        if not np.isfinite(published[c, o]).all():
            continue
        ranks = None if template is None else template[c, o]
        out[c, o] = sample_paths(history, levels, published[c, o], n_paths, ranks)
    return out
