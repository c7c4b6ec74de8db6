"""The context flow (``nf-context``): the paper's masked autoregressive flow over the next weeks of
a hub target, conditioned on an encoder of real context — the target's recent weeks, the other
signal's, the time of year, the climatology's growth at this time of year and the place's scale
(:mod:`pipeline.members.nf.context_features`) — trained globally across every place and week
known at each refit date.

**Pre-training.** The weekly flow's prior (:mod:`pipeline.members.nf.weekly`: the calmed
multi-wave SIRS seen through an admissions layer), cut into windows with the real-context
channels at 0 ("not known") and the scale channel from each trajectory's population: the first
rounds, with a few weeks of history and no other signal released, are served by the prior.

**Refits.** On the refit calendar (:func:`~pipeline.members.nf.real.refit_dates`), the
pre-trained flow is trained further on every (place, week) window of the vintage of that date
whose target weeks had ended ``revision_days`` before it, the other signal and climatology as
released by the vintage's own date (never later), with windows of any extra pool (influenza
admissions of the same 53 places, released by then) and as many synthetic windows as the
``synthetic_share`` asks (the prior's coverage of situations the real data have not shown).
Validation: a seeded share of the places. A cell at origin o uses the latest refit ≤ o.

**Seeds.** The member is ``n_seeds`` such flows, each pre-trained and refitted from its own seed
(initialisation, synthetic windows, validation places), and a cell's paths are drawn from
them in equal shares (a mixture of the seeds' densities). One seed is a noisy estimate: on the
design rounds of COVID-19 admissions three seeds scored 0.816, 0.795 and 0.835 alone, their
mixture 0.783 (``bench/results/nhsn.json``, ``ablations``).

Targets and decoding are the weekly flow's: z_h = logit f_h − logit f_0 (valid paths by
construction), so the member emits joint weekly sample paths (the hub's samples follow their
ranks) as well as quantiles.
"""
from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.errors import ConfigError
from pipeline.fingerprint import fingerprint
from pipeline.members.base import MemberForecast
from pipeline.members.nf.context_features import (ContextChannels, ContextSources, WindowInputs,
                                                  context_windows)
from pipeline.members.nf.context_training import (NF_CONTEXT, TINY_CONTEXT_FLOW,
                                                  TINY_CONTEXT_REFIT, ContextFlowConfig,
                                                  ContextRefitConfig, TrainingPool,
                                                  refit_inputs, refit_windows)
from pipeline.members.nf.flow import (SyntheticWindows, check_horizons, decode_weekly,
                                      last_weeks, path_forecast, sample_cells, StoredFlow,
                                      stored_flow,
                                      weekly_cells)
from pipeline.members.nf.refit import (Refit, RefitJob, estimator_of, fallbacks_of,
                                       mixed_windows, refit_dates, refit_each, refit_for,
                                       stored_refit)
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.panel import Cells, Panel
from pipeline.training.digests import DataDigests

__all__ = ["NF_CONTEXT", "TINY_CONTEXT_FLOW", "TINY_CONTEXT_REFIT", "ContextFlowConfig",
           "ContextRefitConfig", "ContextFlowMember", "TrainingPool", "fit_context_member"]

# ------------------------------------------------------------------------------------ member


Seeds = tuple[Refit, ...]


@dataclass(frozen=True, eq=False)
class ContextFlowMember:
    """``nf-context`` (module docstring): ``models[r]`` the flows (one per seed) refitted at r,
    ``base`` the pre-trained ones (before the first refit); ``sources`` what a cell's context
    reads."""

    base: Seeds
    models: Mapping[pd.Timestamp, Seeds]
    config: ContextFlowConfig
    sources: ContextSources
    channels: ContextChannels = ContextChannels()
    name: str = NF_CONTEXT
    n_samples: int = 1000
    # the refit dates whose refit diverged (in any seed), and what their forecasts use instead
    fallbacks: Mapping[pd.Timestamp, str] = field(default_factory=dict)
    # fingerprints of the refits' flows and of the sources by release date (cell_identity)
    _keys: dict[tuple[str, pd.Timestamp | None], str] = field(
        default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.base or any(len(m) != len(self.base) for m in self.models.values()):
            raise ConfigError(f"{self.name}: every refit needs one flow per seed "
                              f"({len(self.base)})")

    @property
    def max_horizon(self) -> int:
        return self.config.horizon_weeks

    @property
    def n_seeds(self) -> int:
        return len(self.base)

    def refit_for(self, origin: pd.Timestamp) -> pd.Timestamp | None:
        """The latest refit date on or before ``origin`` (None: before the first refit)."""
        return refit_for(self.models, origin)

    def model_for(self, origin: pd.Timestamp) -> Seeds:
        refit = self.refit_for(origin)
        return self.base if refit is None else self.models[refit]

    def cell_identity(self, origin: pd.Timestamp, panel: Panel) -> object:
        """What a cell at ``origin`` from ``panel`` reads (:class:`~pipeline.members.base.
        KeyedByCell`): the flows of its origin's refit and the sources as released by the
        panel's date — not the later refits and releases the member also holds."""
        refit = self.refit_for(origin)
        flows, sources = ("refit", refit), ("sources", panel.as_of)
        if flows not in self._keys:         # the weights hashed once per refit, not per cell
            self._keys[flows] = fingerprint(tuple(estimator_of(m)
                                                  for m in self.model_for(origin)))
        if sources not in self._keys:
            self._keys[sources] = fingerprint(self.sources.released_by(panel.as_of))
        return (self.name, self.config, self.channels, self.n_samples, refit,
                self._keys[flows], self._keys[sources])

    def cell_context(self, cells: Cells, histories: Sequence[WeeklyHistory]
                     ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """The cells' context windows: the other signal and climatology as released by each
        cell's panel's release date (``histories``: the cells' weekly histories, checked)."""
        k, h = self.config.context_weeks, self.config.horizon_weeks
        climate: dict[tuple[pd.Timestamp | None, pd.Timestamp], NDArray[np.float64]] = {}
        for panel, origin in zip(cells.panels, cells.origins):
            if (panel.as_of, origin) not in climate:
                climate[(panel.as_of, origin)] = self.sources.climatology_at(
                    panel.as_of, [origin], h)[0]
        inputs = WindowInputs(
            np.stack([last_weeks(x.cases, k) for x in histories]),
            np.stack([self.sources.other_weeks(p.as_of, place, o, k)
                      for p, place, o in zip(cells.panels, cells.places, cells.origins)]),
            np.array(cells.origins, dtype="datetime64[ns]"),
            np.stack([climate[(p.as_of, o)] for p, o in zip(cells.panels, cells.origins)]),
            np.array([self.sources.people(place, x)
                      for place, x in zip(cells.places, histories)]))
        return context_windows(inputs, self.channels)

    def sample_paths(self, cells: Cells, chunk: int = 16) -> NDArray[np.float64]:
        """Weekly S, I, R paths ``(B, n, H, 3)``, each cell through its origin's refit, its
        draws from the seeds' flows in equal shares (a mixture of their densities)."""
        histories = weekly_cells(cells.histories, self.name)
        context, mask = self.cell_context(cells, histories)
        refits = [self.refit_for(o) for o in cells.origins]
        flows = {r: tuple(estimator_of(m) for m in (self.base if r is None else self.models[r]))
                 for r in set(refits)}
        z = sample_cells([flows[r] for r in refits], context, mask,
                         cells.seeds, self.n_samples, self.config.horizon_weeks, chunk)
        return decode_weekly(z, histories)

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Count quantiles ``(B, H, Q)`` from the sampled paths (kept for the hub's samples)."""
        check_horizons(self.name, horizons, self.max_horizon)
        return path_forecast(self.sample_paths(cells), cells, horizons, levels)


def fit_context_member(config: ContextFlowConfig, refit: ContextRefitConfig,
                       pools: Sequence[TrainingPool], store_root: Path, *,
                       channels: ContextChannels = ContextChannels(), name: str = NF_CONTEXT,
                       n_samples: int = 1000, n_seeds: int = 1,
                       newest_first: bool = False) -> ContextFlowMember:
    """``n_seeds`` pre-trained flows (model store; seed k is both configs' seed + k) each
    refitted at every refit date among the first pool's vintages' last weeks (module
    docstring). ``newest_first``: the last seed and the latest refit first (a second process
    filling the same store from the other end, :mod:`pipeline.training.background`); the
    models are the same either way."""
    if not pools or not pools[0].vintages:
        raise ConfigError(f"{name}: no vintage of the target to train on")
    if n_seeds < 1 or n_samples < n_seeds:
        raise ConfigError(f"{name}: {n_seeds} seeds for {n_samples} draws")
    dates = refit_dates(sorted({p.last_date for _, p in pools[0].vintages}),
                        refit.refit_every_weeks)
    # the real windows cut only where a refit is not stored, once for every seed
    windows = {date: functools.cache(functools.partial(refit_windows, pools, date,
                                                       refit.revision_days, config, channels))
               for date in dates}
    inputs = {date: refit_inputs(pools, date) for date in dates}
    bases: dict[int, Refit] = {}
    seeds: dict[int, dict[pd.Timestamp, Refit]] = {}
    diverged: dict[pd.Timestamp, str] = {}
    for k in (reversed(range(n_seeds)) if newest_first else range(n_seeds)):
        flow = dataclasses.replace(config, seed=config.seed + k)
        again = dataclasses.replace(refit, seed=refit.seed + k)
        synthetic = SyntheticWindows(flow, DataDigests(store_root))
        base = stored_flow(flow, store_root, synthetic=synthetic)
        bases[k] = base.estimator

        def fit(date: pd.Timestamp, flow: ContextFlowConfig = flow,
                again: ContextRefitConfig = again, synthetic: SyntheticWindows = synthetic,
                base: StoredFlow = base) -> Refit | None:
            job = RefitJob(f"{NF_CONTEXT} refit", date, (
                "nf-context refit windows", again.identity(), flow.identity(),
                synthetic.data_sha256, dataclasses.asdict(channels), date, *inputs[date]), {
                f"{NF_CONTEXT} refit": again.identity(), "base": base.key,
                "channels": dataclasses.asdict(channels), "date": str(date.date())})
            cut = functools.cache(lambda: mixed_windows(windows[date](), synthetic.dataset,
                                                        again))
            return stored_refit(job, base.estimator, flow.estimator_config(), cut, again,
                                store_root)

        made = refit_each(dates, fit, name=name, newest_first=newest_first)
        seeds[k] = made.models
        diverged = made.diverged | diverged
    # a date is refitted when every seed has its refit (too few windows: the same for all)
    by_date = {date: tuple(seeds[k][date] for k in range(n_seeds))
               for date in dates if all(date in seeds[k] for k in range(n_seeds))}
    return ContextFlowMember(tuple(bases[k] for k in range(n_seeds)), by_date, config,
                             pools[0].sources, channels, name, n_samples,
                             fallbacks_of(by_date, diverged))
