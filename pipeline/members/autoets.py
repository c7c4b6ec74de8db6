"""statsforecast ``AutoETS`` on log weekly cases: the peer to beat.

The model a user would reach for: ``AutoETS(season_length=1)`` (ETS with the error, trend and
damping chosen by AICc) fitted to log(max(weekly cases, 0.5)) of the complete weeks ending at the
origin, forecast 4 weeks ahead. The hub quantile at level α < 0.5 is the lower end of the
central ``100·(1 − 2α)`` % prediction interval (α > 0.5: the upper end of the ``100·(2α − 1)`` %
one), the median is the point forecast; everything is exponentiated back to counts. I = cases / N:
on the log scale N is a shift, so this is also AutoETS on log weekly I.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from pipeline.members.base import MemberForecast
from pipeline.panels.panel import Cells
from pipeline.panels.targets import TargetError

AUTOETS = "autoets"


@dataclass(frozen=True)
class AutoETSConfig:
    floor_cases: float = 0.5        # log of 0 cases is undefined; 0.5 is half a case
    season_length: int = 1
    min_weeks: int = 4              # fewer complete weeks than this: refuse, naming the origin

    def __post_init__(self) -> None:
        if self.floor_cases <= 0 or self.season_length < 1 or self.min_weeks < 2:
            raise TargetError(f"invalid AutoETSConfig {self}: need floor_cases > 0, "
                              "season_length >= 1, min_weeks >= 2")


def interval_levels(levels: NDArray[np.float64]) -> list[float]:
    """The central-interval levels (percent) whose ends are the hub quantiles, without 0."""
    lv = np.asarray(levels, dtype=np.float64)
    widths = {round(float(100.0 * abs(1.0 - 2.0 * a)), 9) for a in lv}
    return sorted(w for w in widths if w > 0)


def log_quantiles(log_series: NDArray[np.float64], horizons: tuple[int, ...],
                  levels: NDArray[np.float64], config: AutoETSConfig = AutoETSConfig()
                  ) -> NDArray[np.float64]:
    """AutoETS quantiles ``(H, Q)`` on the log scale of ``log_series``."""
    from statsforecast.models import AutoETS

    widths = interval_levels(levels)
    # statsforecast annotates ``level`` as List[int] but takes floats and names the columns after
    # them as given ("lo-95.0" below), so the widths stay floats.
    fc = AutoETS(season_length=config.season_length).forecast(
        y=np.asarray(log_series, dtype=np.float64), h=max(horizons),
        level=cast("list[int]", widths))
    steps = np.asarray(horizons) - 1
    columns = []
    for a in np.asarray(levels, dtype=np.float64):
        width = round(float(100.0 * abs(1.0 - 2.0 * a)), 9)
        if width == 0:
            columns.append(fc["mean"][steps])
        else:
            columns.append(fc[f"{'lo' if a < 0.5 else 'hi'}-{width}"][steps])
    out = np.stack(columns, axis=-1)
    # the ends of nested intervals are monotone up to rounding; make it exact
    return np.maximum.accumulate(out, axis=-1)


@dataclass(frozen=True)
class AutoETSMember:
    config: AutoETSConfig = AutoETSConfig()
    name: str = AUTOETS

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """One AutoETS fit per cell (statsforecast fits a series at a time)."""
        return MemberForecast(np.stack([self._quantiles(h.weekly_cases(), h.origin, horizons,
                                                        levels) for h in cells.histories]))

    def _quantiles(self, weekly: NDArray[np.float64], origin: object, horizons: tuple[int, ...],
                   levels: NDArray[np.float64]) -> NDArray[np.float64]:
        weekly = weekly[np.isfinite(weekly)]
        if weekly.size < self.config.min_weeks:
            raise TargetError(f"autoets at {getattr(origin, 'date', lambda: origin)()}: "
                              f"{weekly.size} complete weeks, needs {self.config.min_weeks}")
        return np.exp(log_quantiles(np.log(np.maximum(weekly, self.config.floor_cases)),
                                    horizons, levels, self.config))
