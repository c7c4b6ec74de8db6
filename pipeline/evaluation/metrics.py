"""Sample-based evaluation metrics: k-NN KL divergence, mean NLL, central-interval coverage.

KL divergence (paper, "Evaluating Distances using Kullback–Leibler Divergence")
-------------------------------------------------------------------------------
The paper compares an estimated density p̂ with the true one p from *samples only*, with the
k-nearest-neighbour estimator of Pérez-Cruz (2008), in the form of Wang, Kulkarni & Verdú (2009,
eq. 25 with k_1 = k_2 = k). For x_1..x_n ~ p̂ and y_1..y_m ~ p in R^d::

    D(p̂ ‖ p) ≈ (d/n) Σ_i log( s_k(x_i) / r_k(x_i) ) + log( m / (n − 1) )

with r_k(x_i) the distance from x_i to its k-th nearest neighbour among the *other* x's and
s_k(x_i) the distance to its k-th nearest neighbour among the y's.

**Sign.** The paper prints ``log(r_k / s_k)``: the ratio is inverted (equivalently, a minus sign is
missing in front of the sum). That form is wrong: it makes the estimate of D(p̂‖p) *decrease* as the
x's move away from the y's. Delecki's reference code (a widely copied gist) computes
``-log(r/s)``, with the comment that the paper misses a negative sign. We implement the correct
form; tests check it against closed-form Gaussian KLs.

Why it works: log(s_k/r_k)·d ≈ log( p̂(x_i) / p(x_i) ) + log((n−1)/m) because the k-NN density
estimate at x_i is k / (count · V_d · dist^d); the volume constants and the digamma corrections
cancel when the same k is used in both sets, so the estimator is consistent (asymptotically
unbiased) for any fixed k.

**k.** The default is k = 1, as in the paper's reference code. Larger k lowers the variance (each
term averages over more neighbours) at the price of more small-sample bias where the density
changes across the k-NN ball (tails, sharp modes). With n, m in the thousands and d ≤ 5, k = 1
gives standard deviations of a few hundredths of a nat (measured in tests/test_metrics.py).

**Duplicate points.** The estimator assumes continuous samples, where ties have probability 0.
Resampled particles (SMC) contain exact copies, which make r_k = 0 (log → +∞) or s_k = 0 (−∞).
We merge coincident points: r_k and s_k are measured to the k-th nearest neighbour at a *positive*
distance, i.e. copies of x_i itself (in either set) are skipped, while each copy still counts as
one of the n terms of the average and in n − 1, m. With no duplicates (the usual case) this is the
formula above exactly.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from scipy.spatial import KDTree

from pipeline.errors import ConfigError

ArrayLike = np.ndarray | torch.Tensor | Sequence[float]

# Central interval levels that match ±1σ, ±2σ, ±3σ of a Gaussian.
SIGMA_LEVELS: tuple[float, float, float] = (0.6826894921370859, 0.9544997361036416,
                                            0.9973002039367398)


def _as_points(name: str, values: ArrayLike) -> np.ndarray:
    """(n,) or (n, d) array-like -> float64 (n, d) array with finite entries."""
    array = values.detach().cpu().numpy() if isinstance(values, torch.Tensor) else np.asarray(values)
    array = np.asarray(array, dtype=np.float64)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2:
        raise ConfigError(f"{name}: expected samples of shape (n,) or (n, d), got {array.shape}")
    if not np.isfinite(array).all():
        bad = int((~np.isfinite(array)).any(axis=1).sum())
        raise ConfigError(f"{name}: {bad} of {len(array)} samples contain NaN or inf")
    return array


def _kth_positive_distance(tree: KDTree, points: np.ndarray, k: int) -> np.ndarray:
    """Distance from each point to its k-th nearest *distinct* neighbour in ``tree``.

    ``tree`` must be built on unique points, so at most one of them coincides with a query point;
    if the nearest one is at distance 0 (a copy of the query) it is skipped.
    """
    distances, _ = tree.query(points, k=k + 1)
    distances = distances.reshape(len(points), k + 1)
    coincident = distances[:, 0] == 0.0
    return np.where(coincident, distances[:, k], distances[:, k - 1])


def knn_kl_divergence(x: ArrayLike, y: ArrayLike, k: int = 1) -> float:
    """k-NN estimate of D(P̂ ‖ Q) in nats from x ~ P̂ (n, d) and y ~ Q (m, d); n and m may differ.

    Correct-sign Pérez-Cruz / Wang–Kulkarni–Verdú form (see the module docstring, which also says
    how duplicate points are handled). 1-D inputs are read as (n, 1). Needs at least k + 1
    distinct points in each set. The result can be slightly negative for P̂ ≈ Q (it is an
    estimate; its expectation is ≈ 0 there).
    """
    if not isinstance(k, int | np.integer) or k < 1:
        raise ConfigError(f"knn_kl_divergence: k must be a positive integer, got {k!r}")
    xs, ys = _as_points("x", x), _as_points("y", y)
    if xs.shape[1] != ys.shape[1]:
        raise ConfigError(f"knn_kl_divergence: x has dimension {xs.shape[1]} but y has "
                          f"{ys.shape[1]}")
    n, d = xs.shape
    m = len(ys)
    x_unique, x_inverse = np.unique(xs, axis=0, return_inverse=True)
    y_unique = np.unique(ys, axis=0)
    if len(x_unique) < k + 1 or len(y_unique) < k + 1:
        raise ConfigError(f"knn_kl_divergence: need at least k+1={k + 1} distinct points in each "
                          f"set, got {len(x_unique)} in x and {len(y_unique)} in y")
    # Within x, the query point itself is always in the tree (distance 0) and is skipped.
    r_k = KDTree(x_unique).query(x_unique, k=k + 1)[0].reshape(-1, k + 1)[:, k]
    s_k = _kth_positive_distance(KDTree(y_unique), x_unique, k)
    log_ratio = np.log(s_k) - np.log(r_k)          # per distinct x point
    total = log_ratio[x_inverse.reshape(-1)].sum()  # each copy counts once
    return float(d * total / n + np.log(m / (n - 1)))


def mean_nll(log_prob_values: ArrayLike) -> float:
    """Mean negative log-likelihood −(1/B) Σ_b log p̂(y_b) of observed values y_b.

    ``log_prob_values`` are the log-densities the *estimated* density assigns to the observed (true)
    values, e.g. ``estimator.log_prob(truth, context, mask)`` or :func:`kde_log_prob` for
    particle/sample sets. Units: nats per observation (of the joint density of all target
    components, i.e. not per dimension). Non-finite values are an error, not silently dropped:
    a −inf means the estimate gave zero density to what happened.
    """
    if np.ndim(log_prob_values) != 1:
        raise ConfigError(f"mean_nll: expected one log-density per observation, shape (B,), got "
                          f"{np.shape(log_prob_values)}")
    values = _as_points("log_prob_values", log_prob_values)[:, 0]
    return float(-values.mean())


def kde_log_prob(samples: torch.Tensor, values: torch.Tensor,
                 bandwidth: float | torch.Tensor | None = None,
                 weights: torch.Tensor | None = None) -> torch.Tensor:
    """Gaussian-KDE log-density of ``values (B, D)`` under sample sets ``samples (B, S, D)``.

    For estimates only available as samples (SMC particles). Diagonal bandwidth per set and
    dimension: Scott's rule h = σ̂ · S_eff^(−1/(D+4)) unless given (scalar or (B, D)).
    ``weights (B, S)`` (non-negative, rows normalized here) make it a weighted KDE; S_eff is then
    Kish's effective sample size. Returns (B,) log-densities; vectorized over B.
    """
    if samples.ndim != 3 or values.ndim != 2 or samples.shape[0] != values.shape[0] \
            or samples.shape[2] != values.shape[1]:
        raise ConfigError(f"kde_log_prob: expected samples (B,S,D) and values (B,D), got "
                          f"{tuple(samples.shape)} and {tuple(values.shape)}")
    batch, count, dim = samples.shape
    if weights is None:
        weights = samples.new_full((batch, count), 1.0 / count)
    else:
        weights = weights / weights.sum(-1, keepdim=True)
    if bandwidth is None:
        mean = (weights[..., None] * samples).sum(1, keepdim=True)
        std = ((weights[..., None] * (samples - mean) ** 2).sum(1)).sqrt()          # (B, D)
        effective = 1.0 / (weights ** 2).sum(-1, keepdim=True)                       # (B, 1)
        bandwidth = std * effective ** (-1.0 / (dim + 4))
    h = torch.as_tensor(bandwidth, dtype=samples.dtype).expand(batch, dim)
    if not bool((h > 0).all()):
        raise ConfigError("kde_log_prob: bandwidth must be positive (are all samples equal?)")
    z = (values[:, None, :] - samples) / h[:, None, :]                                # (B, S, D)
    log_kernel = -0.5 * (z ** 2).sum(-1) - h.log().sum(-1, keepdim=True) \
        - 0.5 * dim * np.log(2.0 * np.pi)
    return torch.logsumexp(log_kernel + weights.log(), dim=-1)


def interval_coverage(samples: ArrayLike, truth: ArrayLike,
                      levels: Sequence[float] = SIGMA_LEVELS) -> np.ndarray:
    """Fraction of forecasts whose truth lies inside the central interval of each level.

    ``samples``: (B, S) or (B, S, D) — S draws for each of B forecasts (and D components);
    ``truth``: (B,) or (B, D). The central interval at level ℓ runs from the empirical
    (1 − ℓ)/2 to the (1 + ℓ)/2 quantile of the S draws (linear interpolation), bounds included.
    Returns an array of shape (L,) or (L, D): coverage per level (and component). A calibrated
    forecast has coverage ≈ ℓ; the defaults are the ±1/2/3σ levels.
    """
    draws = samples.detach().cpu().numpy() if isinstance(samples, torch.Tensor) else np.asarray(
        samples, dtype=np.float64)
    actual = truth.detach().cpu().numpy() if isinstance(truth, torch.Tensor) else np.asarray(
        truth, dtype=np.float64)
    if draws.ndim not in (2, 3) or actual.shape != draws.shape[:1] + draws.shape[2:]:
        raise ConfigError(f"interval_coverage: expected samples (B,S[,D]) and truth (B[,D]), got "
                          f"{draws.shape} and {actual.shape}")
    level_array = np.asarray(levels, dtype=np.float64)
    if level_array.ndim != 1 or ((level_array <= 0) | (level_array >= 1)).any():
        raise ConfigError(f"interval_coverage: levels must lie in (0, 1), got {list(levels)}")
    probs = np.concatenate([(1 - level_array) / 2, (1 + level_array) / 2])
    bounds = np.quantile(draws, probs, axis=1)             # (2L, B[, D])
    lower, upper = bounds[: len(level_array)], bounds[len(level_array):]
    inside = (lower <= actual[None]) & (actual[None] <= upper)
    return inside.mean(axis=1)
