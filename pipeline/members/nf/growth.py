"""The flow member ``nf-growth``: the trained flow (:mod:`pipeline.members.nf.model`) sampled at
each cell's origin, its draws decoded into weekly S, I, R paths (valid by construction) and
their count quantiles; every cell of a batch from its own seed.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

from pipeline.members.base import MemberForecast, quantiles_of_samples
from pipeline.members.nf.model import (N_WEEKS, GrowthModelConfig, RealWindows, cell_noise,
                                       context_features, decode_paths, growth_targets,
                                       single_thread, trailing_week_sums,
                                       train_or_reuse_growth_model)
from pipeline.models.estimator import ConditionalEstimator
from pipeline.panels.history import EpiHistory, History
from pipeline.panels.panel import Cells
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError
from pipeline.progress import ProgressReporter


@dataclass(frozen=True, eq=False)
class NFGrowthMember:
    """Forecast member: samples the trained flow at each cell's origin and decodes weekly
    paths (coordinates: :mod:`pipeline.members.nf.model`)."""

    estimator: ConditionalEstimator
    config: GrowthModelConfig
    name: str = "nf-growth"
    n_samples: int = 1000

    @property
    def max_horizon(self) -> int:
        """The flow forecasts exactly the next ``N_WEEKS`` weeks."""
        return N_WEEKS

    def sample_paths(self, histories: Sequence[History], seeds: Sequence[int],
                     chunk: int = 16) -> NDArray[np.float64]:
        """Weekly S, I, R paths ``(B, n_samples, 4, 3)`` at origin + 7h, h = 1..4, of B daily
        histories (e.g. every county × origin of a backtest) through the flow in calls of
        ``chunk`` histories, history b drawn from ``seeds[b]``. (16 histories × 1,000 draws per
        call: measured 2.3× faster on the CPU than 256, whose activations no longer fit the
        cache.)"""
        daily = [h for h in histories if isinstance(h, EpiHistory)]
        if len(daily) != len(histories):
            raise TargetError(f"{self.name}: the flow reads daily case counts; a weekly series "
                              "needs the weekly flow")
        needed = self.config.context_days + DAYS_PER_WEEK
        short = [h for h in daily if len(h) < needed]
        if short:
            raise TargetError(f"{self.name}: needs {needed} days of history, got "
                              f"{len(short[0])} (origin {short[0].origin.date()})")
        cases = np.stack([h.cases[-needed:] for h in daily])
        week_sums = trailing_week_sums(cases)
        origins = np.full(len(daily), needed - 1)
        context = torch.from_numpy(context_features(week_sums, origins, self.config.context_days))
        mask = torch.ones(context.shape[:2], dtype=torch.bool)
        eps = cell_noise(seeds, self.n_samples, self.estimator.features)
        with torch.no_grad(), single_thread():
            z = torch.cat([self.estimator.noise_to_data(eps[i:i + chunk], context[i:i + chunk],
                                                        mask[i:i + chunk])
                           for i in range(0, len(daily), chunk)]).double().numpy()
        s_before = np.array([h.S[-1 - DAYS_PER_WEEK] for h in daily])[:, None]
        s_origin = np.array([h.S[-1] for h in daily])[:, None]
        population = np.array([h.population for h in daily], dtype=np.int64)[:, None]
        return decode_paths(z, week_sums[:, -1:], s_before, s_origin, population)

    def real_windows(self, histories: Sequence[History], cutoff: pd.Timestamp) -> RealWindows:
        """Every daily window of ``histories`` whose last target week ends on or before
        ``cutoff`` (nf-real's training windows), in this member's coordinates."""
        config = self.config
        contexts, targets, places = [], [], []
        for index, history in enumerate(histories):
            if not isinstance(history, EpiHistory):
                raise TargetError(f"{self.name}: real windows are cut from daily series")
            end = int(np.searchsorted(history.dates.to_numpy(dtype=np.int64), cutoff.value,
                                      side="right")) - 1
            last_origin = end - N_WEEKS * DAYS_PER_WEEK
            if last_origin < config.first_origin:
                continue
            origins = np.arange(config.first_origin, last_origin + 1)
            sums = np.repeat(trailing_week_sums(history.cases)[None], origins.size, axis=0)
            context = context_features(sums, origins, config.context_days)
            with np.errstate(invalid="ignore", divide="ignore"):
                target = growth_targets(sums, np.repeat(history.S[None], origins.size, axis=0),
                                        origins, history.population)
            finite = np.isfinite(target).all(axis=1) & np.isfinite(context).all(axis=(1, 2))
            contexts.append(context[finite])
            targets.append(target[finite])
            places.append(np.full(int(finite.sum()), index, dtype=np.int64))
        if not contexts:
            return RealWindows(np.empty((0, config.context_days, 3), np.float32),
                               np.empty((0, config.context_days), bool),
                               np.empty((0, N_WEEKS), np.float32), np.empty(0, np.int64))
        context = np.concatenate(contexts)
        return RealWindows(context, np.ones(context.shape[:2], dtype=bool),
                           np.concatenate(targets), np.concatenate(places))

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Weekly count quantiles ``(B, H, Q)`` of every cell from its sampled paths (kept)."""
        if max(horizons) > self.max_horizon or min(horizons) < 1:
            raise TargetError(f"{self.name} forecasts weeks 1 … {self.max_horizon}, "
                              f"not {horizons}")
        paths = self.sample_paths(cells.histories, cells.seeds)[:, :, [h - 1 for h in horizons]]
        cases = paths[..., 1] * cells.populations[:, None, None]                # (B, n, H)
        return MemberForecast(quantiles_of_samples(cases, levels), paths=paths)


def default_nf_member(store_root: Path | None = None,
                      config: GrowthModelConfig = GrowthModelConfig(),
                      progress: ProgressReporter | None = None) -> NFGrowthMember:
    """The product's flow member, from the weekly forecast's model store (trained if absent)."""
    if store_root is None:
        from pipeline.training.model_store import default_store_root

        store_root = default_store_root()
    stored = train_or_reuse_growth_model(config, store_root, progress=progress)
    return NFGrowthMember(stored.estimator, config)
