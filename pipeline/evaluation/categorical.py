"""Proper scores of a probability over ordered categories (a pmf), against the observed one:
the ranked probability score (RPS) and the log score, as the hubverse scores FluSight's
rate-change and peak-week targets.

``pmf (..., K)`` sums to 1 over its last axis; ``observed (...)`` is the observed category's
index (``-1``: not observed, scored NaN). Both scores are negatively oriented (lower is better).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipeline.errors import FlowcastError


class CategoricalScoreError(FlowcastError):
    """A pmf that is no probability, or an observed category out of range."""


def _checked(pmf: ArrayLike, observed: ArrayLike
             ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
    p = np.asarray(pmf, dtype=np.float64)
    y = np.asarray(observed, dtype=np.int64)
    if p.shape[:-1] != y.shape:
        raise CategoricalScoreError(f"pmf of shape {p.shape} and observed of shape {y.shape}: "
                                    "one observed category per pmf")
    if (p < 0).any() or not np.allclose(p.sum(axis=-1), 1.0, atol=1e-6):
        raise CategoricalScoreError("each pmf must be non-negative and sum to 1")
    if (y >= p.shape[-1]).any() or (y < -1).any():
        raise CategoricalScoreError(f"observed categories must be 0 … {p.shape[-1] - 1} "
                                    "(or -1: not observed)")
    return p, y, y >= 0


def ranked_probability_score(pmf: ArrayLike, observed: ArrayLike) -> NDArray[np.float64]:
    """RPS = Σ_k (F_k − 1[y ≤ k])² over the K − 1 cumulative probabilities (Epstein 1969; the
    unnormalised form of ``scoringutils``' ``rps_ordinal``): 0 for a sure, right forecast."""
    p, y, seen = _checked(pmf, observed)
    cdf = np.cumsum(p, axis=-1)[..., :-1]
    k = np.arange(p.shape[-1] - 1)
    outcome = (np.where(seen, y, 0)[..., None] <= k).astype(np.float64)
    return np.where(seen, np.sum((cdf - outcome) ** 2, axis=-1), np.nan)


def log_score(pmf: ArrayLike, observed: ArrayLike) -> NDArray[np.float64]:
    """−log p(observed category): infinite for an observed category given probability 0."""
    p, y, seen = _checked(pmf, observed)
    at = np.take_along_axis(p, np.where(seen, y, 0)[..., None], axis=-1)[..., 0]
    with np.errstate(divide="ignore"):
        return np.where(seen, -np.log(at), np.nan)
