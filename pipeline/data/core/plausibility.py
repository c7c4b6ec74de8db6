"""Is each count plausible as *news*, against its own series' recent history? (issues 22, 32)

The validation gate (:mod:`pipeline.data.core.gate`) bounds every count by a share of its place's
population; a count can stay under that and still be no news anyone could believe: the probe of
issue 22 served 99,999,999 new cases on one day of DataSF's open revision window and a spike far
above the series' history. So each count is also held against its own previous rows (days or
weeks, whatever the series' step): at most

    ``jump_factor`` × (median + ``mad_scale`` × 1.4826 × MAD + ``floor``) of the previous
    ``window`` rows,

and, because an epidemic's onset (or a report-date backlog) outruns any median, at least
``growth_factor`` × (the largest count of the previous ``growth_window`` rows + ``floor``). The
robust centre and spread ignore one odd row; the floor keeps a series that starts from zeros from
being refused for a few events. The first row has no history and no bound.

Daily series (:data:`DAILY`: 28 days, growth window 7): on the real SF series the largest ratio
of a count to the median bracket is 4.1 (positives at the start of Omicron, 2021-12-28: 2,325
after a median of 148), and on the six real CDPH vintages (every county, every count column) the
largest ratio of a real count to the combined bound is 0.43 (San Diego's report-date backlog of
5,277 on 2020-05-13); Los Angeles' first wave (2,126 reported on 2020-03-28 after a 28-day median
of 4) passes. Weekly series (:data:`WEEKLY`, NHSN admissions) are in docs/data.md.

:func:`history_bounds` works on many series at once: a (places × rows) array, NaN where a place
has no row.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from pipeline.errors import ConfigError, ValidationError

MAD_TO_SIGMA = 1.4826  # MAD of a normal sample × this = its standard deviation


class ImplausibleCountError(ValidationError):
    """A count far beyond its own history or its place's population: the payload (or the place)
    is refused."""


@dataclass(frozen=True)
class JumpRule:
    """The history bound of the module doc; ``window``/``growth_window`` count rows."""

    window: int = 28
    jump_factor: float = 20.0
    mad_scale: float = 3.0
    floor: int = 50
    growth_factor: float = 20.0
    growth_window: int = 7
    unit: str = "day"

    def __post_init__(self) -> None:
        if (self.window < 1 or self.jump_factor <= 1.0
                or not 1 <= self.growth_window <= self.window):
            raise ConfigError(f"a jump rule needs window >= 1, jump_factor > 1 and 1 <= "
                              f"growth_window <= window, got {self}")


DAILY = JumpRule()


def history_bounds(values: NDArray[np.float64], rule: JumpRule) -> NDArray[np.float64]:
    """Per row (last axis), the largest count its previous ``window`` rows make plausible: inf
    where there is no history. ``values`` is one series or a (places × rows) array with NaN
    where a place has no row."""
    values = np.asarray(values, dtype=np.float64)
    pad = np.full((*values.shape[:-1], rule.window), np.nan)
    history = np.concatenate([pad, values], axis=-1)
    n = values.shape[-1]
    # Window i holds the `window` rows before row i (NaN where the series had not begun).
    windows = sliding_window_view(history, rule.window, axis=-1)[..., :n, :]
    seen = ~np.isnan(windows).all(axis=-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: masked by `seen`
        median = np.nanmedian(windows, axis=-1)
        mad = np.nanmedian(np.abs(windows - median[..., None]), axis=-1)
        recent = windows[..., -rule.growth_window:]
        recent_max = np.nanmax(recent, axis=-1)
    bracket = rule.jump_factor * (median + rule.mad_scale * MAD_TO_SIGMA * mad + rule.floor)
    growth = rule.growth_factor * (np.maximum(np.nan_to_num(recent_max, nan=0.0), 0.0)
                                   + rule.floor)
    recent_seen = ~np.isnan(recent).all(axis=-1)
    bound = np.where(seen, bracket, np.inf)
    return np.where(recent_seen, np.maximum(bound, growth), bound)


@dataclass(frozen=True)
class GrowthRule:
    """A slow ramp no real epidemic has shown (issue 39): the count of ``columns`` over the
    ``days`` rows ending on a row at most ``factor`` × (the same count over the ``days`` rows
    before + ``floor``). Daily case counts (:data:`CASES_GROWTH`): the fastest real growth in
    the six CDPH vintages (every county, episode-date cases, floor 100) is 5.5× (Santa Barbara,
    64 cases in the 7 days to 2020-04-29, then 902 to 2020-05-06: the Lompoc prison outbreak);
    San Francisco's fastest in DataSF's export is 3.5× (Omicron, 1,163 then 4,482 to
    2021-12-23). Twice the CDPH figure is the bound: 11×. A ramp of 2,000 and then 12,000
    cases a day for six days stays under the population bounds (1.4 % of the city a day,
    8.2 % a week) and used to reach the published forecast (a median of 148,822 a week)."""

    columns: tuple[str, ...]
    factor: float = 11.0
    floor: float = 100.0
    days: int = 7

    def __post_init__(self) -> None:
        if self.factor <= 1.0 or self.days < 1 or self.floor < 0:
            raise ConfigError(f"a growth rule needs factor > 1, days >= 1, floor >= 0: {self}")


def growth_sums(values: NDArray[np.float64], rule: GrowthRule
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per row (last axis): the sum over the ``days`` rows ending on it and over the ``days``
    rows before those (NaN where the series has not that much history; missing rows count 0
    once the series has begun)."""
    values = np.asarray(values, dtype=np.float64)
    begun = np.cumsum(~np.isnan(values), axis=-1) > 0
    filled = np.where(np.isnan(values), 0.0, values)
    total = np.concatenate([np.zeros((*values.shape[:-1], 1)), np.cumsum(filled, axis=-1)],
                           axis=-1)
    n, d = values.shape[-1], rule.days
    index = np.arange(n)
    now = total[..., index + 1] - total[..., np.clip(index + 1 - d, 0, None)]
    before = total[..., np.clip(index + 1 - d, 0, None)] - \
        total[..., np.clip(index + 1 - 2 * d, 0, None)]
    # a full earlier window of the series' own rows
    start = np.argmax(begun, axis=-1)[..., None] if values.ndim > 1 else np.argmax(begun)
    enough = index - 2 * d + 1 >= start
    return np.where(enough, now, np.nan), np.where(enough, before, np.nan)


def describe_jump(values: NDArray[np.float64], row: int, rule: JumpRule) -> str:
    """Why row ``row`` of one series is beyond its history bound, for an error message."""
    past = values[max(0, row - rule.window):row]
    past = past[~np.isnan(past)]
    bound = history_bounds(values, rule)[row]
    return (f"more than {rule.jump_factor:g}× the plausible bracket of the previous "
            f"{len(past)} {rule.unit}(s) (median {np.median(past):,.0f}, largest of the last "
            f"{rule.growth_window} {past[-rule.growth_window:].max():,.0f}, bound {bound:,.0f})")
