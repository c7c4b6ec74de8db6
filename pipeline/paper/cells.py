"""One table cell: the mean k-NN KL over the usable windows, beside the paper's value."""
from __future__ import annotations

from typing import NotRequired, TypedDict

import numpy as np
import torch
from torch import Tensor

from pipeline.evaluation.metrics import knn_kl_divergence
from pipeline.inference.reference import ReferencePosterior
from pipeline.paper.config import MIN_REFERENCE_ESS
from pipeline.paper.published import PAPER


class Cell(TypedDict):
    """A cell as stored in paper_tables.json (``collapsed_windows``: Table 1's SMC only)."""

    table: str
    row: str
    col: str
    paper: float
    ours: float
    floor: float
    ess_median: float
    windows_used: int
    windows: int
    collapsed_windows: NotRequired[int]


def mean_kl(estimate: Tensor, reference: Tensor, use: Tensor | None = None) -> float:
    """Mean over the windows in ``use`` (default all) of the k-NN KL D(estimate ‖ reference)."""
    windows = range(estimate.shape[0]) if use is None else torch.nonzero(use).flatten().tolist()
    values = [knn_kl_divergence(estimate[b].numpy(), reference[b].numpy()) for b in windows]
    return float(np.mean(values)) if values else float("nan")


def collapsed_windows(samples: Tensor) -> Tensor:
    """(B,) True where a sample set has fewer than 2 distinct points (k-NN KL undefined: +inf)."""
    return torch.tensor([torch.unique(samples[b], dim=0).shape[0] < 2
                         for b in range(samples.shape[0])])


def usable_windows(*refs: ReferencePosterior) -> Tensor:
    """Windows whose references all have ESS >= MIN_REFERENCE_ESS and are not a point mass.

    A reference collapsed onto one point (e.g. a target before any process noise has moved the
    candidates apart) has no finite k-NN KL against anything: such windows are left out and the
    count used is reported per cell.
    """
    return torch.stack([(r.ess >= MIN_REFERENCE_ESS) & ~collapsed_windows(r.samples)
                        for r in refs]).all(0)


def make_cell(table: str, row: str, col: str, ours: float, floor: float, ess: float,
              use: Tensor) -> Cell:
    return {"table": table, "row": row, "col": col, "paper": PAPER[table][(row, col)],
            "ours": round(ours, 4), "floor": round(floor, 4), "ess_median": round(ess, 1),
            "windows_used": int(use.sum()), "windows": int(use.numel())}
