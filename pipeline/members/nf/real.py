"""The flow member fine-tuned on real series known by the origin (``nf-real``).

The flow member (:mod:`pipeline.members.nf.growth`, or the weekly one) learns growth only from the synthetic
multi-wave prior. Real epidemics have habits the prior does not: how long a wave keeps growing,
how plateaus hold, how fast a decline flattens. This member starts from the same trained flow
and, at every refit date r (every ``refit_every_weeks`` weeks), is fine-tuned on the real
windows of every place of the panel whose four target weeks had ended ``revision_days`` before
r (their counts had settled; the days just before r were still filling in), mixed with as many
synthetic windows from the prior (so the fine-tuned flow keeps the prior's coverage of
situations the real data have not shown yet). A forecast at origin o uses the model of the
latest refit date ≤ o: nothing after the origin enters it. The calendar, the mix, the store and
the fallback of a diverged refit are the refit path's (:mod:`pipeline.members.nf.refit`).

Windows: the same scale-free contexts and valid-by-construction targets as the synthetic ones
(the base member's ``real_windows``), one per day (or week) of each place, in the synthetic model's standardization (the fine-tuned flow is the same model).
Validation: a seeded fifth of the places, for the best-state choice of the trainer.
"""
from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.errors import ConfigError
from pipeline.fingerprint import fingerprint
from pipeline.members.base import Member, MemberForecast
from pipeline.members.nf.flow import FlowConfig, RealWindows, SyntheticWindows
from pipeline.members.nf.refit import (Refit, RefitJob, estimator_of, mixed_windows, refit_copy,
                                       refit_each, refit_for, stored_refit)
from pipeline.models.estimator import ConditionalEstimator
from pipeline.panels.history import History
from pipeline.panels.panel import Cells, Panel
from pipeline.progress import ProgressReporter
from pipeline.training.datasets import WindowedDataset
from pipeline.training.trainer import TrainConfig

NF_REAL = "nf-real"


@dataclass(frozen=True)
class FineTuneConfig:
    """Refit schedule and optimiser of the fine-tuning (module docstring)."""

    refit_every_weeks: int = 4
    revision_days: int = 14
    iterations: int = 300
    batch_size: int = 512
    lr: float = 5e-4
    synthetic_share: float = 0.5
    val_fraction: float = 0.2
    min_windows: int = 500
    seed: int = 0
    # Stop when the validation loss has not improved for this many evaluations (a tenth of the
    # iterations each) and keep the best state: a refit whose loss rises ends there instead of
    # diverging (bench/results/replay.json "refits")
    early_stop_patience: int | None = 2
    grad_clip_norm: float = 1.0

    def __post_init__(self) -> None:
        if (self.refit_every_weeks < 1 or self.revision_days < 0 or self.iterations < 1
                or not 0 <= self.synthetic_share < 1 or not 0 < self.val_fraction < 1
                or self.grad_clip_norm <= 0
                or (self.early_stop_patience is not None and self.early_stop_patience < 1)):
            raise ConfigError(f"invalid FineTuneConfig {self}")

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def train_config(self) -> TrainConfig:
        """The trainer's settings of a refit: cosine schedule, ten evaluations, clipped, early
        stop."""
        return TrainConfig(iterations=self.iterations, batch_size=self.batch_size, lr=self.lr,
                           schedule="cosine", eval_every=max(1, self.iterations // 10),
                           seed=self.seed + 11, grad_clip_norm=self.grad_clip_norm,
                           early_stop_patience=self.early_stop_patience)


class FlowMember(Member, Protocol):
    """A flow member that can be fine-tuned: its trained estimator and settings, its reach, and
    the windows it would train on from real series (the daily flow's, the weekly one's)."""

    @property
    def estimator(self) -> ConditionalEstimator: ...

    @property
    def config(self) -> FlowConfig: ...

    @property
    def max_horizon(self) -> int: ...

    def real_windows(self, histories: Sequence[History], cutoff: pd.Timestamp
                     ) -> RealWindows: ...


@dataclass(frozen=True, eq=False)
class FineTunedGrowthMember:
    """``models[r]``: the flow fine-tuned at refit date r; a cell at origin o is forecast by the
    model of the latest r ≤ o (the synthetic flow before the first refit)."""

    base: FlowMember
    models: Mapping[pd.Timestamp, Refit]
    name: str = NF_REAL
    # the refit dates whose fine-tuning diverged, and what their forecasts use instead
    fallbacks: Mapping[pd.Timestamp, str] = dataclasses.field(default_factory=dict)

    @property
    def max_horizon(self) -> int:
        return self.base.max_horizon

    def refit_for(self, origin: pd.Timestamp) -> pd.Timestamp | None:
        """The latest refit date on or before ``origin`` (None: before the first refit)."""
        return refit_for(self.models, origin)

    @functools.cached_property
    def _base_key(self) -> str:
        return fingerprint(self.base)

    def cell_identity(self, origin: pd.Timestamp, panel: Panel) -> object:
        """What a cell at ``origin`` is forecast with (:class:`~pipeline.members.base.
        KeyedByCell`): the base flow and the refit of its origin, not the later refits (a
        round's refit leaves the earlier rounds' keys as they were)."""
        refit = self.refit_for(origin)
        return (self.name, self._base_key, refit, None if refit is None else self.models[refit])

    def model_for(self, origin: pd.Timestamp) -> FlowMember:
        refit = self.refit_for(origin)
        if refit is None:
            return self.base
        estimator = estimator_of(self.models[refit])
        return dataclasses.replace(self.base, estimator=estimator)  # type: ignore[type-var]

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Every cell through the model of its origin's refit, the cells of each refit in one
        batch (the sample paths kept, as the base member's)."""
        refits = [self.refit_for(o) for o in cells.origins]
        count = np.empty((len(cells), len(horizons), len(levels)))
        paths: NDArray[np.float64] | None = None
        for refit in dict.fromkeys(refits):
            index = [i for i, r in enumerate(refits) if r == refit]
            member = self.base if refit is None else self.model_for(refit)
            made = member.forecast(cells.subset(index), horizons, levels)
            count[index] = made.count
            if made.paths is not None:
                if paths is None:
                    paths = np.empty((len(cells), *made.paths.shape[1:]))
                paths[index] = made.paths
        return MemberForecast(count, paths=paths)


def fit_finetuned_member(base: FlowMember, synthetic: SyntheticWindows,
                         histories: Sequence[History], dates: Sequence[pd.Timestamp],
                         config: FineTuneConfig, store_root: Path | None = None,
                         progress: ProgressReporter | None = None, *,
                         newest_first: bool = False,
                         known_at: Callable[[pd.Timestamp], Sequence[History]] | None = None
                         ) -> FineTunedGrowthMember:
    """Fine-tune at each refit date on ``histories`` as they stood then (module docstring);
    with ``store_root`` every model is kept in the model store (:func:`~pipeline.members.nf.
    refit.stored_refit`), so a rerun on the same data trains nothing and cuts no windows.
    ``newest_first``: the latest date first (:func:`~pipeline.members.nf.refit.refit_each`).
    ``known_at``: the places' data as released by a date (a source with vintages: a refit
    learns from the vintage of its date, not from later revisions of it). A refit that
    diverges is left out: its forecasts come from the previous refit (or the base flow),
    recorded in ``fallbacks``."""

    def fit(date: pd.Timestamp) -> Refit | None:
        known = (list(known_at(date)) if known_at is not None
                 else [h.up_to(date) for h in histories if h.dates[0] <= date])
        windows = functools.cache(functools.partial(
            refit_windows, base, known, date - pd.Timedelta(days=config.revision_days),
            synthetic, config))
        if store_root is None:
            cut = windows()
            return None if cut is None else refit_copy(base.estimator, *cut,
                                                       config.train_config())
        job = RefitJob(NF_REAL, date, ("nf-real windows", config.identity(),
                                       base.config.identity(), synthetic.data_sha256, date,
                                       [h.fingerprint() for h in known]),
                       {NF_REAL: config.identity(), base.config.kind: base.config.identity()})
        return stored_refit(job, base.estimator, base.config.estimator_config(), windows,
                            config, store_root)

    made = refit_each(dates, fit, name=NF_REAL, newest_first=newest_first, progress=progress)
    return FineTunedGrowthMember(base, made.models, fallbacks=made.fallbacks)


def refit_windows(base: FlowMember, known: Sequence[History], cutoff: pd.Timestamp,
                  synthetic: SyntheticWindows, config: FineTuneConfig
                  ) -> tuple[WindowedDataset, WindowedDataset] | None:
    """A refit's (train, validation) windows; None when the places known then have too few."""
    return mixed_windows(base.real_windows(known, cutoff), synthetic.dataset, config)
