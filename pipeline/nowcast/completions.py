"""Nowcast: the final counts of the days still being reported, as samples, never below what has
arrived.

The last weeks of an episode-date series are incomplete (a day's count grows for weeks as late
reports arrive). Given the delay model's completeness draws F_k(d) of each recent day
(:mod:`pipeline.data.california.delays`), each of K completions k draws the final count Y_d of every recent
day d as

    c_d ~ Poisson(λ_d p_d),  Y_d = c_d + Z_d,  Z_d ~ Poisson(λ_d (1 − p_d)),

the thinning of the final count by the share p_d that arrived (p_d ~ Beta(φ F_k(d), φ(1 − F_k(d)))
with the delay model's beta-binomial precision φ: single days scatter around F), and λ_d from a
NobBS-like smooth prior (McGough et al. 2020): log λ_d = a + b·t + weekday, a Poisson regression
of the truncated counts with offset log p_d over the last ``trend_days`` (quasi-likelihood
dispersion for its coefficients' uncertainty, a gamma spread of single days around the trend from
the Pearson residuals). Given λ_d ~ Gamma(κ, κ/μ_d) around the trend μ_d, the unreported part is
negative binomial,

    Z_d | c_d ~ NegBin(size κ + c_d, mean (1 − p_d)(κ + c_d)/(κ/μ_d + p_d)),

so a day that is nearly complete keeps its count (Z small), a day with little reported leans on
the trend, and Y_d ≥ c_d always: a nowcast is never below what has already been reported.

:func:`complete_histories` turns the samples into K histories with the S/I/R conversion's
response to the added cases (S falls by the added cumulative cases, I rises by the added
7-day sum), which the forecast then continues (:mod:`pipeline.nowcast.then_forecast`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.california.delays import DelayModel, lag_days
from pipeline.panels.history import DailySIR, EpiHistory, history_length_up_to
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError

N_TREND_COEFFICIENTS = 2 + 6        # level, slope per week, weekday effects (Monday = 0)
_NEWTON_STEPS = 30


@dataclass(frozen=True)
class NowcastConfig:
    """``n_completions`` K; ``trend_days`` the window of the smooth prior (the days before it
    are final); ``thinning_noise``: single days' completeness scatters (beta) around the delay
    model's F, as the model measured; ``ridge``: prior precision of the trend's slope and
    weekday effects (standard normal)."""

    n_completions: int = 64
    trend_days: int = 28
    thinning_noise: bool = True
    ridge: float = 1.0

    def __post_init__(self) -> None:
        if self.n_completions < 1 or self.trend_days < 2 * DAYS_PER_WEEK or self.ridge < 0:
            raise TargetError(f"invalid NowcastConfig {self}: n_completions >= 1, trend_days "
                              ">= 14 and ridge >= 0 required")


@dataclass(frozen=True, eq=False)
class Nowcast:
    """The nowcast of a history's last days (those within the delay model's ``max_lag`` of the
    data date ``as_of``): ``observed (T,)`` counts as reported, ``samples (K, T)`` final counts
    (≥ ``observed``), ``completeness (K, T)`` the shares each completion assumed arrived."""

    dates: pd.DatetimeIndex
    observed: NDArray[np.int64]
    samples: NDArray[np.int64]
    completeness: NDArray[np.float64]
    as_of: pd.Timestamp

    @property
    def n_completions(self) -> int:
        return int(self.samples.shape[0])

    @property
    def last_date(self) -> pd.Timestamp:
        return self.dates[-1]


# ------------------------------------------------------------------------------ the trend


def trend_design(dates: pd.DatetimeIndex, last: pd.Timestamp) -> NDArray[np.float64]:
    """(T, 8): 1, weeks before ``last`` (≤ 0), weekday indicators Tuesday..Sunday."""
    weeks = ((dates - last).days.to_numpy() / DAYS_PER_WEEK).astype(np.float64)
    weekday = dates.weekday.to_numpy()
    dummies = (weekday[:, None] == np.arange(1, 7)[None, :]).astype(np.float64)
    return np.column_stack([np.ones(len(dates)), weeks, dummies])


def fit_trend(counts: NDArray[np.float64], share: NDArray[np.float64],
              design: NDArray[np.float64], ridge: float
              ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Poisson regression of ``counts (T,)`` with offsets log ``share (K, T)``, one per
    completion: (coefficients (K, P), their covariance (K, P, P) inflated by the Pearson
    dispersion, gamma shape κ (K,) of single days around the trend)."""
    k, p = share.shape[0], design.shape[1]
    penalty = np.full(p, ridge)
    penalty[0] = 0.0                                        # the level is free
    beta = np.zeros((k, p))
    beta[:, 0] = np.log((counts.sum() + 0.5) / np.maximum(share.sum(axis=1), 1e-9))
    log_share = np.log(np.maximum(share, 1e-12))
    for _ in range(_NEWTON_STEPS):
        mean = np.exp(np.clip(beta @ design.T + log_share, -50, 50))         # (K, T)
        gradient = (counts[None, :] - mean) @ design - penalty * beta
        information = np.einsum("kt,tp,tq->kpq", mean, design, design) + np.diag(penalty)
        step = np.linalg.solve(information, gradient[..., None])[..., 0]
        beta = beta + np.clip(step, -5.0, 5.0)
    mean = np.exp(np.clip(beta @ design.T + log_share, -50, 50))
    information = np.einsum("kt,tp,tq->kpq", mean, design, design) + np.diag(penalty)
    resid2 = (counts[None, :] - mean) ** 2
    dof = max(len(counts) - p, 1)
    dispersion = np.maximum((resid2 / np.maximum(mean, 1e-9)).sum(axis=1) / dof, 1.0)
    covariance = np.linalg.inv(information) * dispersion[:, None, None]
    excess = (resid2 - mean).sum(axis=1)
    kappa = np.where(excess > 0, (mean ** 2).sum(axis=1) / np.maximum(excess, 1e-9), 1e6)
    return beta, covariance, kappa


# ---------------------------------------------------------------------------- the nowcast


def draw_shares(completeness: NDArray[np.float64], precision: NDArray[np.float64] | None,
                rng: np.random.Generator) -> NDArray[np.float64]:
    """The share that arrived per completion and day ``(K, T)``: F itself, or beta around it
    with the precision ``(T,)`` of each day."""
    f = np.clip(completeness, 1e-6, 1.0)
    if precision is None:
        return f
    partial = f < 1.0
    shares = f.copy()
    phi = np.broadcast_to(precision[None, :], f.shape)[partial]
    a, b = phi * f[partial], phi * (1.0 - f[partial])
    shares[partial] = np.clip(rng.beta(a, b), 1e-6, 1.0)
    return shares


def sample_final_counts(observed: NDArray[np.int64], dates: pd.DatetimeIndex,
                        completeness: NDArray[np.float64], shares: NDArray[np.float64],
                        config: NowcastConfig, rng: np.random.Generator) -> NDArray[np.int64]:
    """``(K, T)`` final counts ≥ ``observed (T,)`` given the completeness ``(K, T)`` (the
    trend's offsets: a single day's scatter must not tilt the trend) and the shares that
    arrived ``(K, T)`` (the thinning of each day). The trend is fitted to the last
    ``trend_days``; older days (nearly complete) are centred on their own count scaled up."""
    counts = observed.astype(np.float64)
    recent = slice(max(len(dates) - config.trend_days, 0), len(dates))
    design = trend_design(dates, dates[-1])
    beta, covariance, kappa = fit_trend(counts[recent], completeness[:, recent],
                                        design[recent], config.ridge)
    chol = np.linalg.cholesky(covariance + 1e-10 * np.eye(design.shape[1]))
    drawn = beta + np.einsum("kpq,kq->kp", chol, rng.standard_normal(beta.shape))
    trend = np.exp(np.clip(drawn @ design.T, -50, 30))                      # (K, T) μ_d
    older = np.arange(len(dates)) < recent.start
    trend[:, older] = (counts[None, older] + 0.5) / shares[:, older]
    kap = kappa[:, None]
    size = kap + counts[None, :]
    mean_missing = (1.0 - shares) * size / (kap / trend + shares)
    # NegBin(size, mean) as a gamma–Poisson mixture
    rate = rng.gamma(size, np.maximum(mean_missing, 0.0) / size)
    missing = rng.poisson(rate)
    return observed[None, :] + missing.astype(np.int64)


def nowcast_days(history: EpiHistory, as_of: pd.Timestamp, max_lag: int,
                 trend_days: int) -> slice:
    """The history's days within ``max_lag`` of ``as_of``, widened to ``trend_days``."""
    first = pd.Timestamp(as_of) - pd.Timedelta(days=max(max_lag, trend_days) - 1)
    start = int(np.searchsorted(history.dates.to_numpy(dtype=np.int64), first.value))
    if len(history) - start < trend_days:
        raise TargetError(f"a nowcast needs {trend_days} days of history before "
                          f"{pd.Timestamp(as_of).date()}, got {len(history) - start}")
    return slice(start, len(history))


def nowcast_history(history: EpiHistory, model: DelayModel, *, as_of: pd.Timestamp | None = None,
                    county: str | None = None, config: NowcastConfig = NowcastConfig(),
                    seed: int = 0) -> Nowcast:
    """The nowcast of ``history``'s last days as known on ``as_of`` (default: its last day;
    a source that publishes days late, like DataSF, has ``as_of`` after it). ``county``: the
    delay model's county (None: a place it has not seen, e.g. DataSF's San Francisco)."""
    as_of = history.origin if as_of is None else pd.Timestamp(as_of)
    if as_of < history.origin:
        raise TargetError(f"data date {as_of.date()} is before the history's last day "
                          f"{history.origin.date()}")
    days = nowcast_days(history, as_of, model.config.max_lag, config.trend_days)
    dates = history.dates[days]
    observed = history.cases[days].astype(np.int64)
    seeds = np.random.SeedSequence(seed).generate_state(2)
    completeness = model.sample_completeness(config.n_completions, dates=dates, as_of=as_of,
                                             county=county, seed=int(seeds[0]))
    rng = np.random.default_rng(seeds[1])
    # a day's scatter depends on its size; its final count is about c / F
    size = observed / np.maximum(completeness.mean(axis=0), 0.05)
    lags = lag_days(dates, as_of).astype(np.float64)
    shares = draw_shares(completeness,
                         model.precision(size, lags) if config.thinning_noise else None, rng)
    samples = sample_final_counts(observed, dates, np.clip(completeness, 1e-6, 1.0), shares,
                                  config, rng)
    return Nowcast(dates=dates, observed=observed, samples=samples, completeness=completeness,
                   as_of=as_of)


# ------------------------------------------------------------------- completed histories


@dataclass(frozen=True, eq=False)
class CompletedHistories(DailySIR):
    """K copies of a history whose last days hold nowcast samples: ``cases``, ``S``, ``I``,
    ``R`` are (K, T) on ``dates``; :meth:`history` gives one as an :class:`EpiHistory`."""

    first_nowcast_day: pd.Timestamp
    reported: NDArray[np.int64] | None = None       # (T,) the counts as reported, when known

    def __len__(self) -> int:
        return int(self.cases.shape[0])

    def history(self, k: int) -> EpiHistory:
        return EpiHistory(self.dates, self.cases[k], self.S[k], self.I[k], self.R[k],
                          self.population)

    def histories(self, up_to: pd.Timestamp | None = None,
                  count: int | None = None) -> list[EpiHistory]:
        """The first ``count`` completions (default: every one), cut at ``up_to`` (the forecast
        origin) when given."""
        keep = len(self.dates) if up_to is None else history_length_up_to(self.dates, up_to)
        return [EpiHistory(self.dates[:keep], self.cases[k, :keep], self.S[k, :keep],
                           self.I[k, :keep], self.R[k, :keep], self.population)
                for k in range(len(self) if count is None else min(count, len(self)))]


def complete_histories(history: EpiHistory, nowcast: Nowcast) -> CompletedHistories:
    """``history`` with its nowcast days replaced by each completion's final counts; S, I, R
    move as the conversion moves them for added cases (7-day infectious window, deaths kept)."""
    start = int(np.searchsorted(history.dates.to_numpy(dtype=np.int64),
                                nowcast.dates[0].value))
    if not history.dates[start:].equals(nowcast.dates):
        raise TargetError("the nowcast's days are not the end of this history")
    added = np.zeros((nowcast.n_completions, len(history)))
    added[:, start:] = nowcast.samples - nowcast.observed[None, :]
    cumulative = np.cumsum(added, axis=1)
    shifted = np.concatenate([np.zeros((len(added), DAYS_PER_WEEK)),
                              cumulative[:, :-DAYS_PER_WEEK]], axis=1)
    n = float(history.population)
    s = history.S[None, :] - cumulative / n
    i = history.I[None, :] + (cumulative - shifted) / n
    return CompletedHistories(dates=history.dates,
                              cases=history.cases[None, :] + added.astype(np.int64),
                              S=s, I=i, R=1.0 - s - i, population=history.population,
                              first_nowcast_day=nowcast.dates[0],
                              reported=np.asarray(history.cases, dtype=np.int64))


def week_sums(histories: CompletedHistories, ends: Sequence[pd.Timestamp]
              ) -> NDArray[np.float64]:
    """``(K, W)`` cases of the 7-day weeks ending on ``ends`` in every completion."""
    positions = histories.dates.get_indexer(pd.DatetimeIndex(list(ends)))
    if (positions < DAYS_PER_WEEK - 1).any():
        raise TargetError(f"weeks ending {list(ends)} are not all in the history")
    cumulative = np.concatenate([np.zeros((len(histories), 1)),
                                 np.cumsum(histories.cases, axis=1)], axis=1)
    return np.asarray(cumulative[:, positions + 1] - cumulative[:, positions + 1 - DAYS_PER_WEEK],
                      dtype=np.float64)


def day_index(dates: pd.DatetimeIndex, date: pd.Timestamp) -> int:
    """The position of ``date`` in ``dates`` (an error naming it when absent)."""
    pos = int(dates.get_indexer(pd.DatetimeIndex([pd.Timestamp(date)]))[0])
    if pos < 0:
        raise TargetError(f"{pd.Timestamp(date).date()} is not a day of the history "
                          f"({dates[0].date()} … {dates[-1].date()})")
    return pos
