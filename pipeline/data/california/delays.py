"""The reporting-delay (right-truncation) model: how much of a day's final count has arrived.

Fitted from real revisions (:mod:`pipeline.data.california.vintage_pairs`), in the discrete-time hazard form
of epinowcast (Abbott et al.; after Günther et al. 2021 and Höhle & an der Heiden 2014): a case of
day d not yet reported arrives at lag l with probability h(d, l), so the completeness at lag L is

    F(d, L) = 1 − Π_{l=0..L} (1 − h(d, l)),   F(d, L) = 1 for L ≥ ``max_lag`` ("final"),

    logit h(d, l) = α_{bin(l)} + γ_{weekday(d + l)} + x(l)·(u_county + δ_era),

* α: a hazard per lag bin (single days over the first two weeks, wider after), with a
  random-walk prior across bins (smooth where the data are thin);
* γ: the weekday of the *report* day d + l (CDPH reports little at weekends), Monday = 0;
* x(l) = indicators of the lags 0–6, 7–13, 14–27 and 28+: a county's or an era's shift of the
  hazards in each range (the shape changes, not only the speed: in September 2021 the hazard
  fell faster after the second week than in April); counties are partially pooled, u ~ N(0, σ_u²) (a county with little data shrinks to
  the pooled curve); eras (the earlier vintage's date, when the day's reports came in) follow a
  random walk in time, δ_{e+1} − δ_e ~ N(0, σ_δ² · weeks between them), so delays may lengthen
  in a surge and the latest era is extrapolated with growing uncertainty.

Likelihood: an earlier vintage's count of a day given a later vintage's count is beta-binomial,
``early ~ BetaBinomial(late, F(d, L₁)/F(d, L₂), precision φ)`` (the thinning of arrivals, with
overdispersion from batch reporting). The later vintage need not be final: F(d, L₂) < 1 at short
L₂ is part of the ratio, so every pair of vintages contributes.

Fit: the posterior mode (L-BFGS; gradients by torch autograd, imported lazily — this module is
otherwise numpy), and a Laplace approximation (the inverse Hessian at the mode) for the
uncertainty of every parameter; :meth:`DelayModel.sample_completeness` draws completeness from
it. The prior scales σ_u, σ_δ are fixed in :class:`DelayModelConfig`; :func:`log_evidence` (the
Laplace approximation of the marginal likelihood) compares choices (``bench/nowcast.py``).
"""
from __future__ import annotations

import dataclasses
import io
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.california.vintage_pairs import RevisionPairs
from pipeline.errors import ConfigError, FlowcastError
from pipeline.io import atomic_write_bytes

if TYPE_CHECKING:
    import torch

DAYS_PER_WEEK = 7
EFFECT_EDGES: tuple[int, ...] = (0, 7, 14, 28)   # x(l): lags 0–6, 7–13, 14–27, 28+
N_EFFECTS = len(EFFECT_EDGES)
N_WEEKDAYS = 7


class DelayModelError(FlowcastError):
    """A delay model that cannot be fitted (no usable revisions) or asked outside its range."""


@dataclass(frozen=True)
class DelayModelConfig:
    """``bin_edges``: left edges of the hazard's lag bins (the last bin ends at ``max_lag``);
    ``county_sd`` σ_u, ``era_sd_per_week`` σ_δ (per √week), ``lag_smoothness`` the sd of the
    random walk of α across bins; ``first_era_sd`` the prior sd of the first era's shift."""

    max_lag: int = 56
    bin_edges: tuple[int, ...] = (*range(14), 14, 21, 28, 42)
    county_sd: float = 0.5
    era_sd_per_week: float = 0.15
    first_era_sd: float = 0.5
    lag_smoothness: float = 1.0
    max_iterations: int = 500

    def __post_init__(self) -> None:
        edges = np.asarray(self.bin_edges)
        if edges[0] != 0 or (np.diff(edges) <= 0).any() or edges[-1] >= self.max_lag:
            raise ConfigError(f"DelayModelConfig.bin_edges={self.bin_edges} must rise from 0 "
                              f"and stay below max_lag={self.max_lag}")
        for name in ("county_sd", "era_sd_per_week", "first_era_sd", "lag_smoothness"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"DelayModelConfig.{name}={getattr(self, name)} must be > 0")

    @property
    def n_bins(self) -> int:
        return len(self.bin_edges)

    def lag_bin(self) -> NDArray[np.int64]:
        """The bin of every lag 0..max_lag−1."""
        return np.searchsorted(np.asarray(self.bin_edges), np.arange(self.max_lag),
                               side="right").astype(np.int64) - 1


def lag_days(dates: pd.DatetimeIndex, as_of: pd.Timestamp) -> NDArray[np.int64]:
    """Days from each of ``dates`` to ``as_of`` (the lag at which ``as_of`` sees them)."""
    day_ns = pd.Timedelta(days=1).value
    stamps = pd.DatetimeIndex(dates).as_unit("ns").to_numpy(dtype=np.int64)
    return (pd.Timestamp(as_of).value - stamps) // day_ns


def effect_design(max_lag: int) -> NDArray[np.float64]:
    """x(l) for l = 0..max_lag−1: indicators of the lag ranges of :data:`EFFECT_EDGES`,
    shape (max_lag, 4)."""
    group = np.searchsorted(np.asarray(EFFECT_EDGES), np.arange(max_lag), side="right") - 1
    return (group[:, None] == np.arange(N_EFFECTS)[None, :]).astype(np.float64)


@dataclass(frozen=True)
class _Layout:
    """Where each parameter block sits in the flat parameter vector."""

    n_bins: int
    n_counties: int
    n_eras: int

    @property
    def sizes(self) -> dict[str, int]:
        return {"alpha": self.n_bins, "gamma": N_WEEKDAYS - 1,
                "county": self.n_counties * N_EFFECTS, "era": self.n_eras * N_EFFECTS,
                "log_precision": 3}

    @property
    def size(self) -> int:
        return sum(self.sizes.values())

    def slices(self) -> dict[str, slice]:
        out, start = {}, 0
        for name, n in self.sizes.items():
            out[name] = slice(start, start + n)
            start += n
        return out


def _log_hazard_terms(theta: torch.Tensor, layout: _Layout, config: DelayModelConfig
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(α per lag (Lmax,), γ per weekday (7,), county effects (C, 4), era effects (E, 4))."""
    import torch

    s = layout.slices()
    alpha = theta[s["alpha"]][torch.from_numpy(config.lag_bin())]
    gamma = torch.cat([theta.new_zeros(1), theta[s["gamma"]]])
    return (alpha, gamma, theta[s["county"]].reshape(-1, N_EFFECTS),
            theta[s["era"]].reshape(-1, N_EFFECTS))


def completeness_table(alpha: torch.Tensor, gamma: torch.Tensor, shift: torch.Tensor,
                       max_lag: int) -> torch.Tensor:
    """F at lags 0..max_lag for each day weekday: ``shift (..., 4)`` → ``(..., 7, max_lag + 1)``
    (the last column is the final count, 1)."""
    import torch

    lags = torch.arange(max_lag)
    report_weekday = (torch.arange(N_WEEKDAYS)[:, None] + lags[None, :]) % N_WEEKDAYS
    x = torch.from_numpy(effect_design(max_lag)).to(shift.dtype)            # (L, 2)
    logit = (alpha[None, :] + gamma[report_weekday])                         # (7, L)
    logit = logit + (shift @ x.T)[..., None, :]                              # (..., 7, L)
    log_survival = torch.cumsum(torch.nn.functional.logsigmoid(-logit), dim=-1)
    f = -torch.expm1(log_survival)
    return torch.cat([f, torch.ones_like(f[..., :1])], dim=-1)


def _beta_binomial_log_pmf(k: torch.Tensor, n: torch.Tensor, p: torch.Tensor,
                           precision: torch.Tensor, log_choose: torch.Tensor) -> torch.Tensor:
    """log BetaBinomial(k | n, mean p, precision); ``log_choose`` = log C(n, k) (no parameter
    in it, computed once)."""
    import torch

    a, b = precision * p, precision * (1.0 - p)
    lg = torch.lgamma
    return (log_choose + lg(k + a) + lg(n - k + b) - lg(n + precision) + lg(precision)
            - lg(a) - lg(b))


def _normal_log_density(x: torch.Tensor, sd: torch.Tensor | float) -> torch.Tensor:
    import torch

    sd_t = torch.as_tensor(sd, dtype=x.dtype)
    return (-0.5 * (x / sd_t) ** 2 - torch.log(sd_t) - 0.5 * np.log(2 * np.pi)).sum()


@dataclass(frozen=True, eq=False)
class _Data:
    county: Any
    era: Any
    weekday: Any
    lag_early: Any
    lag_late: Any
    early: Any
    late: Any
    log_choose: Any


def _usable(pairs: RevisionPairs, max_lag: int) -> RevisionPairs:
    """Rows that carry information: a later count above 0 and an earlier lag short of final."""
    return pairs.select((pairs.late > 0) & (pairs.lag_early < max_lag))


def _tensors(pairs: RevisionPairs, max_lag: int) -> _Data:
    import torch

    def t(x: NDArray[Any], dtype: torch.dtype = torch.float64) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).to(dtype)
    early, late = t(pairs.early.astype(np.float64)), t(pairs.late.astype(np.float64))
    log_choose = torch.lgamma(late + 1) - torch.lgamma(early + 1) - torch.lgamma(late - early + 1)
    return _Data(county=t(pairs.county, torch.long), era=t(pairs.era, torch.long),
                 weekday=t(pairs.weekday, torch.long),
                 lag_early=t(np.minimum(pairs.lag_early, max_lag), torch.long),
                 lag_late=t(np.minimum(pairs.lag_late, max_lag), torch.long),
                 early=early, late=late, log_choose=log_choose)


def _era_weeks(eras: Sequence[pd.Timestamp]) -> NDArray[np.float64]:
    days = np.diff(np.array([e.value for e in eras], dtype=np.float64)) / 86_400e9
    return np.maximum(days / DAYS_PER_WEEK, 1.0 / DAYS_PER_WEEK)


def _log_prior(theta: torch.Tensor, layout: _Layout, config: DelayModelConfig,
               era_weeks: NDArray[np.float64]) -> torch.Tensor:
    import torch

    s = layout.slices()
    alpha = theta[s["alpha"]]
    era = theta[s["era"]].reshape(-1, N_EFFECTS)
    steps = torch.from_numpy(np.sqrt(era_weeks))[:, None] * config.era_sd_per_week
    return (_normal_log_density(alpha[:1] + 3.0, 3.0)             # weakly: a few % per day
            + _normal_log_density(torch.diff(alpha), config.lag_smoothness)
            + _normal_log_density(theta[s["gamma"]], 1.0)
            + _normal_log_density(theta[s["county"]], config.county_sd)
            + _normal_log_density(era[:1], config.first_era_sd)
            + _normal_log_density(torch.diff(era, dim=0), steps)
            + _normal_log_density(theta[s["log_precision"]][:1] - np.log(100.0), 3.0)
            + _normal_log_density(theta[s["log_precision"]][1:], 1.0))


def _log_likelihood(theta: torch.Tensor, data: _Data, layout: _Layout,
                    config: DelayModelConfig) -> torch.Tensor:
    import torch

    alpha, gamma, county, era = _log_hazard_terms(theta, layout, config)
    shift = county[:, None, :] + era[None, :, :]                              # (C, E, 2)
    table = completeness_table(alpha, gamma, shift, config.max_lag)           # (C, E, 7, L+1)
    f_early = table[data.county, data.era, data.weekday, data.lag_early]
    f_late = table[data.county, data.era, data.weekday, data.lag_late]
    ratio = torch.clamp(f_early / f_late, 1e-9, 1.0 - 1e-9)
    precision = _precision(theta[layout.slices()["log_precision"]], data.late,
                           data.lag_early.to(torch.float64))
    return _beta_binomial_log_pmf(data.early, data.late, ratio, precision,
                                  data.log_choose).sum()


def _precision(coefficients: torch.Tensor, late: torch.Tensor, lag: torch.Tensor
               ) -> torch.Tensor:
    """φ per observation: log φ = c₀ + c₁·log(1 + n/100) + c₂·log(1 + L₁), n the later count,
    L₁ the earlier lag (larger counts scatter less, though not binomially less: batch reporting
    moves whole groups; an old day's last few reports scatter differently from a new day's
    first ones)."""
    import torch

    return torch.exp(coefficients[0] + coefficients[1] * torch.log1p(late / 100.0)
                     + coefficients[2] * torch.log1p(lag))


@dataclass(frozen=True, eq=False)
class DelayModel:
    """A fitted delay model: the posterior mode and its Laplace covariance."""

    config: DelayModelConfig
    counties: tuple[str, ...]
    eras: tuple[pd.Timestamp, ...]
    mode: NDArray[np.float64]
    covariance: NDArray[np.float64]
    log_posterior: float
    n_observations: int
    capped: int
    sources: tuple[str, ...] = field(default=())

    @property
    def _layout(self) -> _Layout:
        return _Layout(self.config.n_bins, len(self.counties), len(self.eras))

    def precision(self, counts: NDArray[np.float64] | float,
                  lags: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """φ of the beta-binomial thinning of a day with ``counts`` final cases seen at
        ``lags`` (larger: closer to binomial)."""
        c0, c1, c2 = self.mode[self._layout.slices()["log_precision"]]
        return np.exp(c0 + c1 * np.log1p(np.asarray(counts, dtype=np.float64) / 100.0)
                      + c2 * np.log1p(np.asarray(lags, dtype=np.float64)))

    def log_evidence(self) -> float:
        """The Laplace approximation of log p(revisions | σ_u, σ_δ)."""
        sign, logdet = np.linalg.slogdet(self.covariance)
        return float(self.log_posterior + 0.5 * len(self.mode) * np.log(2 * np.pi)
                     + 0.5 * logdet) if sign > 0 else float("-inf")

    def parameter_draws(self, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """``(n, P)`` draws from the Laplace posterior (the first is the mode when n > 1 is
        not asked for: every draw is random)."""
        chol = np.linalg.cholesky(self.covariance)
        return self.mode[None, :] + rng.standard_normal((n, len(self.mode))) @ chol.T

    def _era_shift(self, draws: NDArray[np.float64], at: pd.Timestamp,
                   rng: np.random.Generator) -> NDArray[np.float64]:
        """δ at date ``at`` per draw: the latest era on or before it, plus the random walk's
        spread over the weeks since (the first era, before all of them)."""
        era = draws[:, self._layout.slices()["era"]].reshape(len(draws), -1, N_EFFECTS)
        dates = np.array([e.value for e in self.eras])
        k = int(np.searchsorted(dates, pd.Timestamp(at).value, side="right")) - 1
        k = max(k, 0)
        weeks = abs(pd.Timestamp(at) - self.eras[k]).days / DAYS_PER_WEEK
        walk = rng.standard_normal((len(draws), N_EFFECTS)) * self.config.era_sd_per_week \
            * np.sqrt(weeks)
        return era[:, k] + walk

    def _county_shift(self, draws: NDArray[np.float64], county: str | None,
                      rng: np.random.Generator) -> NDArray[np.float64]:
        """u per draw: the county's own (partially pooled) effect, or, for a place the model
        has not seen (``None`` or an unknown name), a new county from N(0, σ_u²)."""
        if county is not None and county in self.counties:
            effects = draws[:, self._layout.slices()["county"]].reshape(len(draws), -1,
                                                                       N_EFFECTS)
            return effects[:, self.counties.index(county)]
        return rng.standard_normal((len(draws), N_EFFECTS)) * self.config.county_sd

    def completeness_draws(self, n: int, *, at: pd.Timestamp, county: str | None,
                           seed: int) -> NDArray[np.float64]:
        """``(n, 7, max_lag + 1)``: F by the day's weekday and lag, one row per posterior draw,
        for ``county`` (None: a new place) with reports arriving around date ``at``."""
        import torch

        rng = np.random.default_rng(seed)
        draws = self.parameter_draws(n, rng)
        shift = self._county_shift(draws, county, rng) + self._era_shift(draws, at, rng)
        tables = []
        for theta, s in zip(draws, shift, strict=True):
            alpha, gamma, _, _ = _log_hazard_terms(torch.from_numpy(theta), self._layout,
                                                   self.config)
            tables.append(completeness_table(alpha, gamma, torch.from_numpy(s),
                                             self.config.max_lag))
        return torch.stack(tables).numpy()

    def sample_completeness(self, n: int, *, dates: pd.DatetimeIndex, as_of: pd.Timestamp,
                            county: str | None, seed: int) -> NDArray[np.float64]:
        """``(n, T)`` completeness of each of ``dates`` as known on ``as_of`` (lag
        ``as_of − date``; 1 beyond ``max_lag``, and for days after ``as_of`` an error)."""
        lags = lag_days(dates, as_of)
        if (lags < 0).any():
            raise DelayModelError(f"days after the data date {pd.Timestamp(as_of).date()} have "
                                  "no completeness")
        tables = self.completeness_draws(n, at=as_of, county=county, seed=seed)
        weekday = pd.DatetimeIndex(dates).weekday.to_numpy()
        return tables[:, weekday, np.minimum(lags, self.config.max_lag)]

    def predictive_ratio(self, pairs: RevisionPairs, n: int, seed: int) -> NDArray[np.float64]:
        """``(n, rows)`` draws of the share of the later count already in the earlier one, for
        the rows of ``pairs`` (counties and eras by name and date, so a held-out era gets the
        random walk's interpolation). A pair that skips vintages is the chain of the links in
        between, each with its own era's curve: Π_k F_k(d, v_k − d) / F_k(d, v_{k+1} − d)."""
        import torch

        rng = np.random.default_rng(seed)
        draws = self.parameter_draws(n, rng)
        county_shift = np.stack([self._county_shift(draws, c, rng) for c in pairs.counties],
                                axis=1)                                           # (n, C, 4)
        era_shift = np.stack([self._era_shift(draws, e, rng) for e in pairs.eras],
                             axis=1)                                              # (n, E, 4)
        offsets = np.array([(v - pairs.vintage_dates[0]).days for v in pairs.vintage_dates])
        out = np.ones((n, len(pairs)))
        for i, theta in enumerate(draws):
            alpha, gamma, _, _ = _log_hazard_terms(torch.from_numpy(theta), self._layout,
                                                   self.config)
            shift = torch.from_numpy(county_shift[i][:, None, :] + era_shift[i][None, :, :])
            table = completeness_table(alpha, gamma, shift, self.config.max_lag).numpy()
            for k in range(len(pairs.eras)):
                link = (pairs.era <= k) & (pairs.later > k)
                lag_k = pairs.lag_early[link] + offsets[k] - offsets[pairs.era[link]]
                lag_next = lag_k + offsets[k + 1] - offsets[k]
                idx = (pairs.county[link], np.full(int(link.sum()), k), pairs.weekday[link])
                out[i, link] *= (table[(*idx, np.minimum(lag_k, self.config.max_lag))]
                                 / table[(*idx, np.minimum(lag_next, self.config.max_lag))])
        return np.clip(out, 0.0, 1.0)

    def pooled_curve(self, n: int, *, at: pd.Timestamp | None = None, seed: int = 0,
                     new_county: bool = False) -> NDArray[np.float64]:
        """``(n, max_lag + 1)`` draws of the completeness by lag averaged over the day's
        weekday, for the pooled county (u = 0; ``new_county``: a new county's spread) at
        the era of ``at`` (default: the latest era)."""
        import torch

        rng = np.random.default_rng(seed)
        draws = self.parameter_draws(n, rng)
        at = self.eras[-1] if at is None else at
        shift = self._era_shift(draws, at, rng)
        if new_county:
            shift = shift + rng.standard_normal(shift.shape) * self.config.county_sd
        curves = []
        for theta, s in zip(draws, shift, strict=True):
            alpha, gamma, _, _ = _log_hazard_terms(torch.from_numpy(theta), self._layout,
                                                   self.config)
            curves.append(completeness_table(alpha, gamma, torch.from_numpy(s),
                                             self.config.max_lag).mean(0))
        return torch.stack(curves).numpy()


def fit_delay_model(pairs: RevisionPairs, config: DelayModelConfig = DelayModelConfig(),
                    sources: tuple[str, ...] = ()) -> DelayModel:
    """The posterior mode and Laplace covariance of the delay model on ``pairs``."""
    import torch

    usable = _usable(pairs, config.max_lag)
    if len(usable) == 0:
        raise DelayModelError("no revision carries information (every later count is 0 or "
                              f"every earlier lag is at least {config.max_lag} days)")
    layout = _Layout(config.n_bins, len(pairs.counties), len(pairs.eras))
    data = _tensors(usable, config.max_lag)
    era_weeks = _era_weeks(pairs.eras)

    def negative_log_posterior(theta: torch.Tensor) -> torch.Tensor:
        return -(_log_likelihood(theta, data, layout, config)
                 + _log_prior(theta, layout, config, era_weeks))

    theta = torch.zeros(layout.size, dtype=torch.float64)
    theta[layout.slices()["alpha"]] = -2.0
    theta[layout.slices()["log_precision"].start] = np.log(100.0)
    theta.requires_grad_(True)
    optimizer = torch.optim.LBFGS([theta], lr=1.0, max_iter=config.max_iterations,
                                  tolerance_grad=1e-7, tolerance_change=1e-10,
                                  history_size=50, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        loss = negative_log_posterior(theta)
        loss.backward()
        return loss

    optimizer.step(closure)
    mode = theta.detach().clone()
    hessian = torch.autograd.functional.hessian(negative_log_posterior, mode, vectorize=True)
    assert isinstance(hessian, torch.Tensor)
    symmetric = 0.5 * (hessian + hessian.T)
    covariance = _inverse_positive_definite(symmetric.numpy())
    return DelayModel(config=config, counties=pairs.counties, eras=pairs.eras,
                      mode=mode.numpy(), covariance=covariance,
                      log_posterior=-float(negative_log_posterior(mode)),
                      n_observations=len(usable), capped=pairs.capped, sources=sources)


def _inverse_positive_definite(hessian: NDArray[np.float64]) -> NDArray[np.float64]:
    """H⁻¹, with the smallest eigenvalues floored (a flat direction: wide, not infinite)."""
    values, vectors = np.linalg.eigh(hessian)
    floor = max(float(values.max()) * 1e-10, 1e-8)
    if values.min() < -1e-6 * abs(values.max()):
        raise DelayModelError(f"the delay model's fit is not at a minimum (Hessian eigenvalue "
                              f"{values.min():.3g}); more iterations are needed")
    return (vectors / np.maximum(values, floor)) @ vectors.T


def save_delay_model(model: DelayModel, path: str | os.PathLike[str]) -> None:
    """Write a fitted model (atomically) for :func:`load_delay_model`."""
    meta = {"config": dataclasses.asdict(model.config), "counties": list(model.counties),
            "eras": [str(e.date()) for e in model.eras], "log_posterior": model.log_posterior,
            "n_observations": model.n_observations, "capped": model.capped,
            "sources": list(model.sources)}
    buffer = io.BytesIO()
    np.savez(buffer, mode=model.mode, covariance=model.covariance,
             meta=np.array(json.dumps(meta)))
    atomic_write_bytes(path, buffer.getvalue())


def load_delay_model(path: str | os.PathLike[str], config: DelayModelConfig) -> DelayModel:
    """A model written by :func:`save_delay_model` for ``config`` (else ``DelayModelError``)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            mode, covariance = data["mode"], data["covariance"]
    except (OSError, KeyError, ValueError) as exc:
        raise DelayModelError(f"cannot read the delay model {path}: {exc}") from exc
    if meta["config"] != json.loads(json.dumps(dataclasses.asdict(config))):
        raise DelayModelError(f"the delay model {path} was fitted with another config")
    return DelayModel(config=config, counties=tuple(meta["counties"]),
                      eras=tuple(pd.Timestamp(e) for e in meta["eras"]), mode=mode,
                      covariance=covariance, log_posterior=float(meta["log_posterior"]),
                      n_observations=int(meta["n_observations"]), capped=int(meta["capped"]),
                      sources=tuple(meta["sources"]))


def log_evidence(pairs: RevisionPairs, config: DelayModelConfig) -> float:
    """The Laplace approximation of the marginal likelihood of ``pairs`` under ``config``."""
    return fit_delay_model(pairs, config).log_evidence()
