"""The settings of a paper-tables run: sizes (:class:`BenchConfig`), where it reads and writes
(:class:`Locations`), the tables' rows and columns, and the protocol text stored with the results.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

ENCODERS: tuple[str, ...] = ("transformer", "transformer-ke", "mamba")
ENCODER_LABEL = {"transformer": "Transformer", "transformer-ke": "Transformer + KE",
                 "mamba": "Mamba-SSM"}
LOCATIONS: tuple[str, ...] = ("before", "at", "after")
LOCATION_LABEL = {"before": "Before-bifurcation", "at": "At-bifurcation",
                  "after": "After-bifurcation"}
# Target times of the three locations (R = 5 observations; the switch acts from t = 5.5 on).
# t = 0 is never a target: every vehicle starts at the origin, a point mass (KL undefined).
VEHICLE_FULL_TARGETS = {"forward": {"before": 5.0, "at": 8.0, "after": 14.0},
                        "backward": {"before": 1.0, "at": 3.0, "after": 9.0}}
VEHICLE_DROPOUT_TARGETS = {"forward": {"before": 5.0, "at": 8.0, "after": 13.0},
                           "backward": {"before": 1.5, "at": 3.5, "after": 9.0}}
DIR_LABEL = {"forward": "fw", "backward": "bw"}
# Windows whose reference has fewer effective candidates than this are left out of the mean
# (their "truth" is a handful of points); the count used is reported per cell.
MIN_REFERENCE_ESS = 20.0

# How the cells are computed; stored as ``protocol`` in paper_tables.json.
PROTOCOL = """\
* Models: the presets of :mod:`pipeline.training.presets` with the ``fast`` recipe, capped by a per-model
  wall-clock budget (the cosine schedule is compressed to end annealed at the budget). Table 1 uses
  the ``vehicle`` preset on the fixed-step ``vehicle-full`` data (Δt = 1); Table 2 the ``vehicle``
  preset (``vehicle-dropout``); Tables 3/4 ``sir-single`` and ``sir-multi``. Encoders: transformer,
  transformer + KE, Mamba; forward and backward.
* Test windows come from freshly simulated trajectories (seeds unseen in training).
  Vehicle: ``n_windows`` trajectories per location; the target is the (kept) time nearest the
  location's time with R = 5 kept observations before (fw) / after (bw) it. Locations: before
  the switch (context entirely before t = 5.5), at it (context straddles it), after it.
  SIR: 100 random target positions (uniform over the valid positions; single: along one fresh
  noisy realisation of the fixed trajectory; multi: one position on each of 100 fresh
  trajectories with (β, γ) from the prior).
* "True distribution" = the reference posterior of :mod:`pipeline.inference.reference` (simulator draws
  weighted by the likelihood of the window's observations), 1,000 draws.
* KL: ``knn_kl_divergence(model samples, reference draws)`` = D(estimate ‖ truth), k = 1,
  1,000 vs 1,000 samples; 2-D (p_x, p_y) for the vehicle, 1-D per compartment for SIR; the
  mean over windows is reported.
* SMC (Table 1): bootstrap filter (:mod:`pipeline.inference.smc`, vehicle model) with 1,000 particles
  started from the prior around the first context observation o_n (not weighted by it again),
  four steps with observation updates (o_{n+1} … o_{n+4}), one propagation without (the
  paper's protocol), particles resampled by weight.
* KL floor: the same KL between two references built from independent candidate sets."""


@dataclass(frozen=True)
class BenchConfig:
    """Sizes of one run. ``quick`` shrinks everything to check the pipeline end to end."""

    quick: bool = False
    n_samples: int = 1000
    n_vehicle_windows: int = 100
    n_sir_locations: int = 100
    vehicle_candidates: int = 20_000
    sir_parameter_draws: int = 1000
    sir_substeps: int = 2
    # The committed run's budgets (docs/estimation.md): SIR 200 s, vehicle 360 s per model.
    train_budget_s: float = 200.0
    vehicle_train_budget_s: float | None = 360.0  # None: train_budget_s
    train_iterations: int | None = None
    n_trajectories: dict[str, int] | None = None  # per dataset name; None: the presets' sizes
    seed: int = 0

    @classmethod
    def quick_config(cls) -> BenchConfig:
        return cls(quick=True, n_samples=300, n_vehicle_windows=6, n_sir_locations=4,
                   vehicle_candidates=3000, sir_parameter_draws=100, sir_substeps=1,
                   train_budget_s=10.0, vehicle_train_budget_s=None, train_iterations=40,
                   n_trajectories={"vehicle-full": 300, "vehicle-dropout": 300,
                                   "sir-single": 20, "sir-multi": 20})


@dataclass(frozen=True)
class Locations:
    """Where a run writes: ``results`` (paper_tables*.json/md and ``figures/``) and ``work``
    (the trained-checkpoint cache, keyed by model and budget). Figure paths in the JSON are
    relative to ``root`` (absolute when outside it)."""

    results: Path
    work: Path
    root: Path

    @classmethod
    def under(cls, root: Path) -> Locations:
        """The repository layout: ``<root>/bench/results`` and ``<root>/bench/work``."""
        return cls(results=root / "bench" / "results", work=root / "bench" / "work", root=root)

    def display(self, path: Path) -> str:
        """``path`` relative to ``root`` when it lies under it, else as given."""
        return str(path.relative_to(self.root)) if path.is_relative_to(self.root) else str(path)
