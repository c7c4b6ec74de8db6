"""Sample paths of the published forecast, and the count of invalid values in them.

Weekly S/I/R paths at origin + 7h from the published count quantiles: ensemble copula coupling
(Schefzik, Thorarinsdottir & Gneiting 2013) with the ranks of a member's paths when given (their
weekly counts N·I_h), else comonotone draws (one level per path). I_h = C_h/N,
S_h = S_{h−1} − C_h/N from the observed S at the origin (C_h at most the remaining susceptibles
N·S_{h−1}, a physical bound), R_h = 1 − S_h − I_h. Non-negative, S non-increasing and R
non-decreasing by construction (R_h − R_{h−1} = C_{h−1}/N ≥ 0, with C_0 = N·I at the origin);
:func:`count_invalid` checks it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.combine.average import EnsembleError
from pipeline.evaluation.quantile_function import quantiles_at
from pipeline.panels.history import History

ROUNDING = 1e-12


def path_levels(n_paths: int, horizons: int, ranks_from: NDArray[np.float64] | None
                ) -> NDArray[np.float64]:
    """Levels ``(n, H)`` of each path's weekly cases: comonotone (k − ½)/n, or ECC: the levels
    in the order of the ranks of ``ranks_from (n, H)`` (a member's weekly cases per path)."""
    base = (np.arange(n_paths) + 0.5) / n_paths
    if ranks_from is None:
        return np.repeat(base[:, None], horizons, axis=1)
    if ranks_from.shape != (n_paths, horizons):
        raise EnsembleError(f"copula template has shape {ranks_from.shape}, expected "
                            f"{(n_paths, horizons)}")
    ranks = np.argsort(np.argsort(ranks_from, axis=0, kind="stable"), axis=0, kind="stable")
    return base[ranks]


def sample_paths(history: History, levels: NDArray[np.float64],
                 case_quantiles: NDArray[np.float64], n_paths: int,
                 template_paths: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Weekly S/I/R paths ``(n, H, 3)`` at origin + 7h from case quantiles ``(H, Q)``."""
    n_h = case_quantiles.shape[0]
    n = float(history.population)
    template = None
    if template_paths is not None:
        if template_paths.shape[0] < n_paths or template_paths.shape[1] != n_h:
            raise EnsembleError(f"template paths {template_paths.shape} do not give {n_paths} "
                                f"paths over {n_h} horizons")
        template = template_paths[:n_paths, :, 1] * n        # weekly cases = N·I (L = 7)
    u = path_levels(n_paths, n_h, template)                      # (n, H)
    draws = quantiles_at(levels, case_quantiles, u.T, unit=1.0).T           # (n, H)
    s_prev = np.full(n_paths, float(history.susceptible_at_weeks()[-1]))
    out = np.empty((n_paths, n_h, 3))
    for k in range(n_h):
        cases = np.minimum(draws[:, k], n * s_prev)              # at most the susceptibles
        s_new = np.where(cases >= n * s_prev, 0.0, s_prev - cases / n)
        i_new = cases / n
        out[:, k, 0], out[:, k, 1] = s_new, i_new
        out[:, k, 2] = 1.0 - s_new - i_new
        s_prev = s_new
    return out


@dataclass(frozen=True)
class InvalidCounts:
    negative_fractions: int
    s_increases: int
    r_decreases: int
    negative_rates: int

    @property
    def total(self) -> int:
        return self.negative_fractions + self.s_increases + self.r_decreases + self.negative_rates

    def to_dict(self) -> dict[str, int]:
        return {"negative_fractions": self.negative_fractions, "s_increases": self.s_increases,
                "r_decreases": self.r_decreases, "negative_rates": self.negative_rates,
                "total": self.total}


def count_invalid(paths: NDArray[np.float64], start: NDArray[np.float64],
                  rates: NDArray[np.float64] | None = None) -> InvalidCounts:
    """Invalid values in ``paths (n, H, 3)`` starting from the observed ``start (3,)`` S, I, R:
    negative fractions, S increases, R decreases (each step, the first from the start), and
    negative rates in ``rates (n, ...)`` when given. A change of a share smaller than
    :data:`ROUNDING` is rounding (R_h = 1 − S_h − I_h moves by exactly I_{h−1}, which is 0 in a
    week without cases), not a decrease."""
    full = np.concatenate([np.broadcast_to(start, (paths.shape[0], 1, 3)), paths], axis=1)
    return InvalidCounts(
        negative_fractions=int((paths < 0).sum()),
        s_increases=int((np.diff(full[..., 0], axis=1) > ROUNDING).sum()),
        r_decreases=int((np.diff(full[..., 2], axis=1) < -ROUNDING).sum()),
        negative_rates=int((rates < 0).sum()) if rates is not None else 0)


def add_counts(a: InvalidCounts, b: InvalidCounts) -> InvalidCounts:
    return InvalidCounts(a.negative_fractions + b.negative_fractions,
                         a.s_increases + b.s_increases, a.r_decreases + b.r_decreases,
                         a.negative_rates + b.negative_rates)
