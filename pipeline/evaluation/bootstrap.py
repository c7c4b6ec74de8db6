"""How sure a backtest's coverage is: a moving-block bootstrap over its origins.

A backtest's forecasts are not independent draws. Every place's forecast from one origin sees
the same week of the epidemic, and the horizons of neighbouring origins score the same
outcomes, so resampling single forecasts makes an interval far too narrow. Resampling blocks
of consecutive origins, each with all its places and horizons, keeps both dependencies (the
moving-block bootstrap, Künsch 1989). The block is as long as the longest horizon: origins
closer than that share outcome weeks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class BlockBootstrap:
    """``block``: consecutive origins per block (None: the number of horizons); ``draws``
    resamples; the central ``level`` percentile interval; ``seed`` makes it reproducible."""

    block: int | None = None
    draws: int = 2000
    level: float = 0.95
    seed: int = 0

    def __post_init__(self) -> None:
        if (self.block is not None and self.block < 1) or self.draws < 10 \
                or not 0.0 < self.level < 1.0:
            raise ConfigError(f"invalid {self}: block >= 1, draws >= 10, 0 < level < 1")


def ratio_interval(numerators: NDArray[np.float64], denominators: NDArray[np.float64],
                   block: int, config: BlockBootstrap = BlockBootstrap()
                   ) -> tuple[float, float] | None:
    """The percentile interval of Σ numerators / Σ denominators, both ``(O,)`` per origin in
    time order, under the moving-block bootstrap of origins; None without any denominator."""
    n = len(numerators)
    if n == 0 or float(np.sum(denominators)) <= 0:
        return None
    block = max(1, min(block, n))
    rng = np.random.default_rng(config.seed)
    starts = rng.integers(0, n - block + 1, size=(config.draws, -(-n // block)))
    index = (starts[..., None] + np.arange(block)).reshape(config.draws, -1)[:, :n]
    num, den = numerators[index].sum(axis=1), denominators[index].sum(axis=1)
    ratios = num[den > 0] / den[den > 0]
    tail = (1.0 - config.level) / 2
    low, high = np.quantile(ratios, [tail, 1.0 - tail])
    return float(low), float(high)


def coverage_interval(covered: NDArray[np.float64], mask: NDArray[np.bool_],
                      config: BlockBootstrap = BlockBootstrap()) -> tuple[float, float] | None:
    """The interval of the share covered among the cells ``mask`` keeps; ``covered`` and
    ``mask`` are ``(C, O, H)`` (covered: 1, 0, or NaN where not scored)."""
    kept = mask & np.isfinite(covered)
    hits = np.where(kept, covered, 0.0).sum(axis=(0, 2))
    counts = kept.sum(axis=(0, 2)).astype(np.float64)
    block = config.block if config.block is not None else covered.shape[2]
    return ratio_interval(hits, counts, block, config)
