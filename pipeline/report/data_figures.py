"""Figures of the data: the SF S/I/R series, and the SF series beside the synthetic SIR prior
ensemble (``flowcast data plot``).

The comparison answers: does the real series lie inside what the flow is trained on? The prior
ensemble is the paper's ``sir-multi`` (beta ~ U[0.02, 0.04], gamma ~ U[0.005, 0.025], S0 = 0.99,
I0 = 0.01, R0 = 0, dt = 1 day), simulated with ``pipeline.systems.sir.simulate_sir`` (RK4).

Time alignment (stated because the result depends on it): SF day k (k = 0 on the first day of the
converted series, 2020-03-03) is compared with simulation day ``offset + k``. ``offset = 0`` pins
the start of the SF epidemic to the prior's initial condition; ``best_offset`` searches every
offset for the one with the most SF days inside the envelope (an optimistic alignment).

"Inside" means the SF value lies in the pointwise 1 %–99 % quantile band of the ensemble on the
aligned day, for each compartment and for all three at once. Two bands are measured: of the
noiseless *states* (the flow's targets) and of the *observations* (state + N(0, sigma^2) noise,
sigma = 0.027, the flow's context).
"""
from __future__ import annotations

import os
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from pipeline.data.sf.sir_transform import SIRSeries
from pipeline.names import COMPARTMENTS

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclass(frozen=True)
class PriorEnsembleConfig:
    beta: tuple[float, float] = (0.02, 0.04)
    gamma: tuple[float, float] = (0.005, 0.025)
    s0: float = 0.99
    i0: float = 0.01
    r0: float = 0.0
    horizon_days: int = 1000
    obs_sigma: float = 0.027
    n_trajectories: int = 500
    quantiles: tuple[float, float] = (0.01, 0.99)
    seed: int = 0


@dataclass(frozen=True)
class EnvelopeFit:
    offset: int
    inside: dict[str, float]          # fraction of SF days inside, per compartment and "all"


@dataclass(frozen=True)
class PriorComparison:
    prior: PriorEnsembleConfig
    n_days: int
    states_aligned: EnvelopeFit       # offset 0, noiseless states
    states_best: EnvelopeFit          # best offset, noiseless states
    observations_aligned: EnvelopeFit  # offset 0, noisy observations
    sf_max_infected: float = 0.0
    prior_median_peak_infected: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)


def simulate_prior(prior: PriorEnsembleConfig) -> tuple[np.ndarray, np.ndarray]:
    """(states, observations), each (N, horizon+1, 3) float64, reproducible from ``prior.seed``."""
    import torch  # lazy: plotting the SF series alone must not need torch

    from pipeline.systems.sir import simulate_sir

    generator = torch.Generator().manual_seed(prior.seed)
    n = prior.n_trajectories
    uniform = torch.rand((2, n), generator=generator, dtype=torch.float64)
    beta = prior.beta[0] + (prior.beta[1] - prior.beta[0]) * uniform[0]
    gamma = prior.gamma[0] + (prior.gamma[1] - prior.gamma[0]) * uniform[1]
    x0 = torch.tensor([prior.s0, prior.i0, prior.r0], dtype=torch.float64).expand(n, 3)
    states = simulate_sir(x0.contiguous(), beta, gamma, prior.horizon_days, 1.0)
    noise = torch.randn(states.shape, generator=generator, dtype=torch.float64)
    return states.numpy(), (states + prior.obs_sigma * noise).numpy()


def envelope(ensemble: np.ndarray, quantiles: tuple[float, float]) -> np.ndarray:
    """(2, T, 3): lower and upper pointwise quantiles over trajectories."""
    return np.quantile(ensemble, quantiles, axis=0)


def fraction_inside(sf: np.ndarray, band: np.ndarray, offset: int) -> dict[str, float]:
    """Share of SF days (sf: (K, 3)) inside band[:, offset:offset+K] per compartment and jointly."""
    window = band[:, offset: offset + len(sf)]
    k = window.shape[1]
    inside = (sf[:k] >= window[0]) & (sf[:k] <= window[1])
    result = {name: float(inside[:, j].mean()) for j, name in enumerate(COMPARTMENTS)}
    result["all"] = float(inside.all(axis=1).mean())
    return result


def best_offset(sf: np.ndarray, band: np.ndarray) -> EnvelopeFit:
    """The alignment with the most SF days inside (all three compartments), vectorized."""
    k = len(sf)
    n_offsets = band.shape[1] - k + 1
    if n_offsets < 1:
        return EnvelopeFit(0, fraction_inside(sf, band, 0))
    idx = np.arange(n_offsets)[:, None] + np.arange(k)[None, :]        # (O, K)
    lo, hi = band[0][idx], band[1][idx]                                 # (O, K, 3)
    joint = ((sf[None] >= lo) & (sf[None] <= hi)).all(axis=2).mean(axis=1)
    offset = int(np.argmax(joint))
    return EnvelopeFit(offset, fraction_inside(sf, band, offset))


def compare_with_prior(sir: SIRSeries, prior: PriorEnsembleConfig = PriorEnsembleConfig()
                       ) -> PriorComparison:
    sf = sir.frame[list(COMPARTMENTS)].to_numpy()
    states, observations = simulate_prior(prior)
    state_band = envelope(states, prior.quantiles)
    obs_band = envelope(observations, prior.quantiles)
    return PriorComparison(
        prior=prior, n_days=len(sf),
        states_aligned=EnvelopeFit(0, fraction_inside(sf, state_band, 0)),
        states_best=best_offset(sf, state_band),
        observations_aligned=EnvelopeFit(0, fraction_inside(sf, obs_band, 0)),
        sf_max_infected=float(sf[:, 1].max()),
        prior_median_peak_infected=float(np.median(states[:, :, 1].max(axis=1))))


def _pyplot():  # noqa: ANN202 - the pyplot module, its type inferred from the import
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_sir_series(sir: SIRSeries, path: str | os.PathLike[str]) -> Path:
    """Three stacked panels S, I, R (proportions) against date; vintage in the title."""
    from pipeline.io import atomic_open

    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for ax, name, color in zip(axes, COMPARTMENTS, ("tab:blue", "tab:red", "tab:green")):
        ax.plot(sir.frame["date"], sir.frame[name], color=color, lw=1.2)
        ax.set_ylabel(f"{name} (proportion)")
        ax.grid(alpha=0.3)
    conversion = sir.provenance.conversion
    vintage = sir.provenance.series.vintage
    fig.suptitle(f"San Francisco COVID-19 as S/I/R (N={conversion.population:,}, "
                 f"L={conversion.infectious_period_days} d, ascertainment "
                 f"{'on' if conversion.ascertainment else 'off'})\n"
                 f"data as of {vintage.data_as_of}, kept through {vintage.last_date_kept}",
                 fontsize=9)
    fig.tight_layout()
    return _save(fig, path, atomic_open, plt)


def plot_sir_vs_prior(sir: SIRSeries, prior: PriorEnsembleConfig,
                      path: str | os.PathLike[str], comparison: PriorComparison | None = None
                      ) -> Path:
    """SF S/I/R over the prior ensemble's 1–99 % state band and a few trajectories (offset 0)."""
    from pipeline.io import atomic_open

    plt = _pyplot()
    states, _ = simulate_prior(prior)
    band = envelope(states, prior.quantiles)
    days = np.arange(states.shape[1])
    sf = sir.frame[list(COMPARTMENTS)].to_numpy()
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for j, (ax, name) in enumerate(zip(axes, COMPARTMENTS)):
        ax.fill_between(days, band[0, :, j], band[1, :, j], color="0.8",
                        label=f"prior {int(prior.quantiles[0]*100)}–"
                              f"{int(prior.quantiles[1]*100)} % band")
        ax.plot(days, states[:20, :, j].T, color="0.55", lw=0.5)
        ax.plot(np.arange(len(sf)), sf[:, j], color="tab:red", lw=1.5, label="San Francisco")
        ax.set_title(name)
        ax.set_xlabel("day (SF day 0 = 2020-03-03 aligned with t = 0)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    text = (f"prior β∈{prior.beta}, γ∈{prior.gamma}, I0={prior.i0}")
    if comparison is not None:
        text += (f"; SF days inside (all three): {comparison.states_aligned.inside['all']:.0%} "
                 f"at offset 0, {comparison.states_best.inside['all']:.0%} at best offset "
                 f"{comparison.states_best.offset}")
    fig.suptitle(text, fontsize=9)
    fig.tight_layout()
    return _save(fig, path, atomic_open, plt)


def _save(fig: Figure, path: str | os.PathLike[str],
          atomic_open: Callable[[Path, str], AbstractContextManager[IO[Any]]],
          plt: ModuleType) -> Path:
    target = Path(path)
    with atomic_open(target, "wb") as handle:
        fig.savefig(handle, format=target.suffix.lstrip(".") or "png", dpi=120)
    plt.close(fig)
    return target
