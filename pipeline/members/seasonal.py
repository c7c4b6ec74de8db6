"""A seasonal member: how the epidemic grew at this time of year in earlier seasons (``seasonal``).

COVID-19 in the US has had two waves a year since 2022, a winter one and a late-summer one, at
much the same weeks. For each step s ahead, the member pools the log growth
g = log(1 + x_{w+s}) − log(1 + x_w) of a long **climatology** series over every place and every
earlier week w whose week of the year is within ``band`` weeks of the origin's, counting only
growth windows that ended at least ``min_age_weeks`` before the origin (earlier seasons, not the
current one); the forecast of a place is its last value (nowcast) times e^{quantiles of g}.

The climatology is the NSSP ED-visit share, reported weekly since 2022-10 (the admissions
series of the hub begins in 2024-11: a season and a half, too short to learn a season from). A
cell uses the climatology as known at its vintage (``as_of`` of its panel): the newest
climatology vintage released by then; with none released by then the member has no forecast
(NaN), and the published average is over the members that have one.

It assumes this year's waves come when 2022–24's did; its skill on the hub's rounds, alone and
in the published average, is measured by ``bench/nhsn.py`` (docs/forecasting.md).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.members.base import MemberForecast
from pipeline.panels.panel import Cells, Panel, known_by, weeks_ending
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError

SEASONAL = "seasonal"
WEEKS_PER_YEAR = 52


@dataclass(frozen=True)
class SeasonalConfig:
    """``band``: weeks of the year either side of the origin's that count; ``min_age_weeks``:
    a growth window must have ended that long before the origin (earlier seasons only)."""

    band: int = 2
    min_age_weeks: int = 26

    def __post_init__(self) -> None:
        if self.band < 0 or self.min_age_weeks < 1:
            raise TargetError(f"invalid SeasonalConfig {self}: band >= 0, min_age_weeks >= 1")


def week_of_year(dates: pd.DatetimeIndex) -> NDArray[np.int64]:
    return np.asarray(dates.isocalendar().week, dtype=np.int64)


def seasonal_growth(climatology: Panel, origin: pd.Timestamp, steps: Sequence[int],
                    levels: NDArray[np.float64], config: SeasonalConfig) -> NDArray[np.float64]:
    """Quantiles ``(S, Q)`` of the past log growth over each step at the origin's time of
    year, pooled over the climatology's places (module docstring); NaN without any."""
    n_weeks = int((pd.Timestamp(origin) - climatology.first_date).days // DAYS_PER_WEEK) + 1
    if n_weeks < 2:
        return np.full((len(steps), len(levels)), np.nan)
    logs = np.log1p(np.maximum(np.stack([weeks_ending(h, origin, n_weeks)
                                         for h in climatology.histories.values()]), 0.0))
    ends = pd.date_range(end=pd.Timestamp(origin), periods=n_weeks, freq="7D")
    distance = np.abs(week_of_year(ends) - week_of_year(pd.DatetimeIndex([origin]))[0])
    near = np.minimum(distance, WEEKS_PER_YEAR - distance) <= config.band
    out = np.full((len(steps), len(levels)), np.nan)
    for k, step in enumerate(steps):
        last_start = n_weeks - 1 - config.min_age_weeks - step
        starts = np.flatnonzero(near[:max(last_start + 1, 0)])
        growth = logs[:, starts + step] - logs[:, starts]
        growth = growth[np.isfinite(growth)]
        if growth.size:
            out[k] = np.quantile(growth, levels)
    return out


@dataclass(frozen=True, eq=False)
class SeasonalGrowthMember:
    """``seasonal`` (module docstring): ``climatology`` holds the climatology's vintages by
    release date (the cell's own panel when empty: a long series forecasting itself)."""

    climatology: Sequence[tuple[pd.Timestamp, Panel]] = ()
    config: SeasonalConfig = SeasonalConfig()
    name: str = SEASONAL
    # the hub's: the climatology is another series (the ED share); none released yet means no
    # forecast, not the cell's own short series
    climatology_required: bool = False

    def source_for(self, panel: Panel) -> Panel | None:
        """The climatology as known when ``panel`` was released."""
        if not self.climatology:
            return None if self.climatology_required else panel
        if panel.as_of is None:
            raise TargetError(f"{self.name}: the cell's panel has no release date to choose "
                              "the climatology known then")
        return known_by(self.climatology, panel.as_of)

    def cell_identity(self, origin: pd.Timestamp, panel: Panel) -> object:
        """What a cell from ``panel`` reads (:class:`~pipeline.members.base.KeyedByCell`):
        the climatology as known when the panel was released — the panel itself when it is
        its own — not the releases that came later."""
        return (self.name, self.config, self.climatology_required, self.source_for(panel))

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        levels = np.asarray(levels, dtype=np.float64)
        out = np.full((len(cells), len(horizons), len(levels)), np.nan)
        groups: dict[tuple[int, pd.Timestamp], list[int]] = {}
        for b, (panel, origin) in enumerate(zip(cells.panels, cells.origins)):
            groups.setdefault((id(panel), origin), []).append(b)
        for (_, origin), index in groups.items():
            source = self.source_for(cells.panels[index[0]])
            if source is None:
                continue
            growth = seasonal_growth(source, origin, horizons, levels, self.config)
            last = np.array([cells.histories[b].weekly_cases()[-1] for b in index])
            out[index] = np.expm1(np.log1p(np.maximum(last, 0.0))[:, None, None]
                                  + growth[None])
        return MemberForecast(np.maximum(out, 0.0))
