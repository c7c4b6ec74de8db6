"""Double-moon demo of the kinetic-energy term (paper, Figure "nf_ke_prelim").

An unconditional MAF (``context_features = 0``: the base mean and log-scale are free parameters)
is trained twice on the two-moons distribution from the same initialisation and the same
batches: once by maximum likelihood, once with the kinetic term added. For both we record every
layer's output f_0 = x, ..., f_L = z on held-out points (the figure: 2 rows x L+1 panels), the
held-out NLL, and the path lengths E||f_{l+1} - f_l||:
- ``path_length_total`` = sum over l = 0 .. L-1 (the whole path from data to base);
- ``kinetic_sum`` = sum over l = 1 .. L-1 (what the kinetic term penalises, without 1/(L-1)).
The paper's claim is that the kinetic term shortens the path.

The two moons are generated here with numpy (as scikit-learn's ``make_moons``: two interleaved
half circles, Gaussian noise), centred at the origin.
"""
from __future__ import annotations

import dataclasses
import io
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.io import atomic_write_bytes, atomic_write_json
from pipeline.training.kinetic import KineticWeights, kinetic_loss, path_lengths
from pipeline.models.maf import Backend, ConditionalFlow, FlowConfig, build_flow
from pipeline.progress import ProgressReporter, SilentProgress

MOONS_CENTRE = np.array([0.5, 0.25])


@dataclass(frozen=True)
class KineticDemoConfig:
    iterations: int = 3000
    batch_size: int = 512
    layers: int = 6
    hidden_features: int = 32
    learning_rate: float = 2e-3
    noise: float = 0.08
    kinetic: KineticWeights = field(default_factory=lambda: KineticWeights(1.0, 0.1, 0.0))
    backend: Backend = "zuko"
    eval_points: int = 4000
    seed: int = 0


def two_moons(n: int, noise: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 2), moon label (n,)): upper half circle and the shifted lower one."""
    label = rng.integers(0, 2, size=n)
    angle = rng.uniform(0.0, np.pi, size=n)
    upper = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    lower = np.stack([1.0 - np.cos(angle), 0.5 - np.sin(angle)], axis=1)
    points = np.where(label[:, None] == 0, upper, lower) + noise * rng.standard_normal((n, 2))
    return points - MOONS_CENTRE, label


@dataclass(frozen=True)
class TrainedFlowSummary:
    weights: KineticWeights
    heldout_nll: float
    path_length_total: float
    kinetic_sum: float
    per_layer_path_length: list[float]
    train_seconds: float


def _empty_context(n: int) -> torch.Tensor:
    return torch.empty(n, 0)


def train_unconditional(config: KineticDemoConfig, weights: KineticWeights,
                        progress: ProgressReporter | None = None) -> tuple[ConditionalFlow, float]:
    """Train one flow; initialisation and batches depend only on ``config.seed``."""
    progress = progress or SilentProgress()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        flow = build_flow(FlowConfig(2, 0, layers=config.layers,
                                     hidden_features=config.hidden_features,
                                     backend=config.backend))
    rng = np.random.default_rng(config.seed)
    optimizer = torch.optim.Adam(flow.parameters(), lr=config.learning_rate)
    start = time.perf_counter()
    for _ in range(config.iterations):
        points, _ = two_moons(config.batch_size, config.noise, rng)
        x = torch.as_tensor(points, dtype=torch.float32)
        loss = kinetic_loss(flow, x, _empty_context(len(x)), weights=weights)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        progress.advance(1, loss=float(loss.detach()))
    return flow, time.perf_counter() - start


@torch.no_grad()
def summarize(flow: ConditionalFlow, weights: KineticWeights, points: np.ndarray,
              seconds: float) -> tuple[TrainedFlowSummary, list[np.ndarray]]:
    x = torch.as_tensor(points, dtype=torch.float32)
    outputs = flow.layer_outputs(x, _empty_context(len(x)))
    lengths = path_lengths(outputs)
    nll = -float(flow.log_prob(x, _empty_context(len(x))).mean())
    summary = TrainedFlowSummary(weights, nll, float(lengths.sum()), float(lengths[1:].sum()),
                                 [float(v) for v in lengths], seconds)
    return summary, [o.numpy() for o in outputs]


def plot_layer_outputs(rows: dict[str, list[np.ndarray]], labels: np.ndarray) -> bytes:
    """PNG: one row per trained flow, one panel per layer output f_0 .. f_L."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_panels = len(next(iter(rows.values())))
    figure, axes = plt.subplots(len(rows), n_panels, figsize=(2.2 * n_panels, 2.4 * len(rows)),
                                squeeze=False)
    for r, (title, outputs) in enumerate(rows.items()):
        for l, values in enumerate(outputs):
            ax = axes[r, l]
            ax.scatter(values[:, 0], values[:, 1], c=labels, s=1.5, cmap="coolwarm", alpha=0.6)
            ax.set_xlim(-4, 4)
            ax.set_ylim(-4, 4)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(("x = f_0" if l == 0 else f"f_{l}") if r == 0 else "", fontsize=9)
        axes[r, 0].set_ylabel(title, fontsize=9)
    figure.suptitle("Layer outputs from data (left) to base (right)")
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    return buffer.getvalue()


def run_kinetic_demo(config: KineticDemoConfig, out_dir: str | Path,
                     progress: ProgressReporter | None = None) -> dict[str, Any]:
    """Train both flows, write ``kinetic_layers.png`` and ``kinetic_demo.json`` into
    ``out_dir``; return the JSON content."""
    out = Path(out_dir)
    points, labels = two_moons(config.eval_points, config.noise,
                               np.random.default_rng(config.seed + 10_000))
    runs = {"maximum likelihood": KineticWeights(),
            "with kinetic term": config.kinetic}
    summaries, trajectories = {}, {}
    for name, weights in runs.items():
        flow, seconds = train_unconditional(config, weights, progress)
        summaries[name], trajectories[name] = summarize(flow, weights, points, seconds)
    atomic_write_bytes(out / "kinetic_layers.png", plot_layer_outputs(trajectories, labels))
    plain, kinetic = summaries["maximum likelihood"], summaries["with kinetic term"]
    result = {
        "config": dataclasses.asdict(config),
        "maximum_likelihood": dataclasses.asdict(plain),
        "with_kinetic_term": dataclasses.asdict(kinetic),
        "path_length_ratio": kinetic.path_length_total / plain.path_length_total,
        "heldout_nll_difference": kinetic.heldout_nll - plain.heldout_nll,
        "figure": "kinetic_layers.png",
    }
    atomic_write_json(out / "kinetic_demo.json", result)
    return result
