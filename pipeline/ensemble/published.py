"""The published ensemble for many histories known at one vintage, as one batched forecaster.

The weekly run publishes the equal-weight average of log(1 + quantile) of four members
(docs/forecasting.md "The forecast"): ``hub-baseline``, ``growth-qr``, ``nf-growth`` and
``nf-real``. :class:`PublishedEnsemble` forecasts many histories of one vintage at once — every
county, every completion of its nowcast — with those members, as the run forecasts San
Francisco:

* ``hub-baseline``, ``nf-growth``, ``nf-real`` see each history alone, in batches
  (:func:`~pipeline.ensemble.panel.forecast_cells`);
* ``growth-qr`` pools each history with the vintage's places (``pool``, as the run pools San
  Francisco with California's counties) less the history's own place (``places``), all
  histories in one batch (:func:`~pipeline.ensemble.growth_regression.pooled_growth_forecast_batch`).

**Reach.** The flows forecast exactly four weeks (``max_horizon``). Beyond a member's reach its
quantiles are NaN. The published forecast there is missing (``beyond_reach="missing"``, the
default: the run never asks for more than four weeks), or, with ``"reachable-members"``, the
same log average over the members that do reach it — a different forecaster, which whoever asks
for it must name as such (``bench/nowcast.py``'s drop-14 comparison at five and six weeks).

Members' quantiles are exposed (:meth:`PublishedEnsemble.member_quantiles`) with the
combination (:meth:`PublishedEnsemble.combine`), so that a nowcast's completions are mixed per
member before the members are averaged — the order of the weekly run's
:class:`~pipeline.ensemble.nowcast_forecast.CompletionMixture`.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from pipeline.ensemble.combine import PUBLISHED, EnsembleError, vincentize
from pipeline.ensemble.growth_regression import (GROWTH_QR, GrowthRegressionConfig,
                                                 pooled_growth_forecast_batch)
from pipeline.ensemble.members import Member
from pipeline.ensemble.panel import BatchMember, BatchTargetsMember, forecast_cells
from pipeline.ensemble.targets import EpiHistory

BeyondReach = Literal["missing", "reachable-members"]
AnyMember = Member | BatchMember | BatchTargetsMember


@runtime_checkable
class LimitedReach(Protocol):
    """A member that forecasts at most ``max_horizon`` weeks ahead (the flows: four)."""

    @property
    def max_horizon(self) -> int: ...


def reachable(member: object, horizons: tuple[int, ...]) -> tuple[int, ...]:
    """The horizons ``member`` can forecast."""
    if isinstance(member, LimitedReach):
        return tuple(h for h in horizons if h <= member.max_horizon)
    return horizons


@dataclass(frozen=True, eq=False)
class PublishedEnsemble:
    """The published forecast of histories of one vintage (module docstring): ``members`` seen
    one history at a time, plus ``growth-qr`` pooled over ``pool`` (places by name)."""

    members: tuple[AnyMember, ...]
    pool: Mapping[str, EpiHistory]
    regression: GrowthRegressionConfig = GrowthRegressionConfig()
    beyond_reach: BeyondReach = "missing"
    name: str = PUBLISHED

    def __post_init__(self) -> None:
        if self.beyond_reach not in ("missing", "reachable-members"):
            raise EnsembleError(f"beyond_reach={self.beyond_reach!r}: use 'missing' or "
                                "'reachable-members'")

    @property
    def member_names(self) -> tuple[str, ...]:
        return (GROWTH_QR, *(m.name for m in self.members))

    @property
    def full_reach(self) -> int | None:
        """The longest horizon every member forecasts (None: unlimited)."""
        limits = [m.max_horizon for m in self.members if isinstance(m, LimitedReach)]
        return min(limits) if limits else None

    def member_quantiles(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                         levels: NDArray[np.float64], seed: int,
                         places: Sequence[str | None] | None = None) -> NDArray[np.float64]:
        """Weekly case quantiles ``(M, B, H, Q)`` of every member (order: ``member_names``),
        NaN beyond a member's reach; history b's place ``places[b]`` is left out of
        growth-qr's pool."""
        levels = np.asarray(levels, dtype=np.float64)
        names = list(self.pool)
        own = [names.index(p) if p is not None and p in self.pool else None
               for p in (places if places is not None else [None] * len(histories))]
        out = np.full((len(self.members) + 1, len(histories), len(horizons), len(levels)),
                      np.nan)
        out[0] = pooled_growth_forecast_batch(histories, list(self.pool.values()), horizons,
                                              levels, self.regression, excluded=own)
        for m, member in enumerate(self.members, start=1):
            steps = reachable(member, horizons)
            if steps:
                index = [horizons.index(h) for h in steps]
                out[m][:, index] = forecast_cells(member, histories, steps, levels,
                                                  seed)["cases"]
        return out

    def combine(self, member_quantiles: NDArray[np.float64]) -> NDArray[np.float64]:
        """The published quantiles ``(..., Q)`` from the members' ``(M, ..., Q)``: equal
        weights on log(1 + q); where a member is missing, NaN or (``reachable-members``) the
        average of those present."""
        present = np.asarray(np.isfinite(member_quantiles).all(axis=-1))      # (M, ...)
        m = member_quantiles.shape[0]
        complete = vincentize(np.where(present[..., None], member_quantiles, 0.0),
                              np.full(m, 1.0 / m), scale="log")
        everyone = np.asarray(present.all(axis=0))[..., None]
        if self.beyond_reach == "missing":
            return np.where(everyone, complete, np.nan)
        logs = np.where(present[..., None], np.log1p(np.maximum(member_quantiles, 0.0)), 0.0)
        count = np.asarray(present.sum(axis=0))[..., None]
        with np.errstate(invalid="ignore", divide="ignore"):
            partial = np.expm1(logs.sum(axis=0) / count)
        return np.where(everyone, complete, np.where(count > 0, partial, np.nan))

    def __call__(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int,
                 places: Sequence[str | None] | None = None) -> NDArray[np.float64]:
        """Published weekly case quantiles ``(B, H, Q)``."""
        return self.combine(self.member_quantiles(histories, horizons, levels, seed, places))
