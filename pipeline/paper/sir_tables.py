"""Tables 3 and 4: SIR with fixed (``sir-single``) and random (``sir-multi``) parameters, KL per
compartment S, I, R for the three encoders, forward and backward, at random target positions."""
from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from pipeline.inference.reference import (SIRReferenceConfig, simulate_sir_candidates,
                                          sir_reference)
from pipeline.paper.cells import Cell, make_cell, mean_kl, usable_windows
from pipeline.paper.config import DIR_LABEL, ENCODER_LABEL, ENCODERS, BenchConfig, Locations
from pipeline.paper.models import RequiredModel, model_samples, trained_estimator
from pipeline.names import DIRECTIONS


def sir_windows(prior_name: str, direction: str, n: int,
                seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """B test windows (values (B,5,3), times (B,5), target (B,)) at random positions."""
    from pipeline.systems.sir import simulate_ensemble

    single = prior_name == "sir-single"
    ens = simulate_ensemble(prior_name, n_trajectories=1 if single else n, seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    n_times = ens.times.shape[0]
    positions = torch.randint(5, n_times, (n,), generator=gen) if direction == "forward" \
        else torch.randint(0, n_times - 5, (n,), generator=gen)
    traj = torch.zeros(n, dtype=torch.long) if single else torch.arange(n)
    offsets = torch.arange(-5, 0) if direction == "forward" else torch.arange(1, 6)
    idx = positions[:, None] + offsets[None]
    return ens.observations[traj[:, None], idx], ens.times[idx], ens.times[positions]


def sir_cells(cfg: BenchConfig, locations: Locations) -> tuple[list[Cell], dict[str, float]]:
    """The cells of Tables 3 and 4 and their KL floors."""
    from pipeline.systems.sir import get_prior

    cells: list[Cell] = []
    floors: dict[str, float] = {}
    ref_cfg = SIRReferenceConfig(n_parameter_draws=cfg.sir_parameter_draws,
                                 substeps=cfg.sir_substeps, n_draws=cfg.n_samples)
    for table, prior_name in (("Table 3", "sir-single"), ("Table 4", "sir-multi")):
        prior = get_prior(prior_name)
        # One fixed trajectory is cheap to refine: a 16x finer τ grid keeps its ESS up near the
        # peak, where a 5-day window pins τ down to about half a day.
        table_cfg = dataclasses.replace(ref_cfg, substeps=16) if prior.parameters_fixed else ref_cfg
        cand_a = simulate_sir_candidates(prior, table_cfg, seed=11)
        cand_b = simulate_sir_candidates(prior, table_cfg, seed=22)
        for direction in DIRECTIONS:
            values, times, target = sir_windows(prior_name, direction, cfg.n_sir_locations,
                                                seed=7000 + (direction == "backward"))
            offsets = times - target[:, None]
            ref = sir_reference(cand_a, offsets, values, cfg.n_samples, seed=1)
            ref_b = sir_reference(cand_b, offsets, values, cfg.n_samples, seed=2)
            row = DIR_LABEL[direction]
            use = usable_windows(ref, ref_b)
            floor = {c: mean_kl(ref.samples[..., i:i + 1], ref_b.samples[..., i:i + 1], use)
                     for i, c in enumerate("SIR")}
            for c, v in floor.items():
                floors[f"{table} / {row} / {c}"] = v
            for encoder in ENCODERS:
                est = trained_estimator(RequiredModel(prior_name, encoder, direction), cfg,
                                        locations)
                samples = model_samples(est, values, times, target, cfg.n_samples, seed=3)
                for i, c in enumerate("SIR"):
                    kl = mean_kl(samples[..., i:i + 1], ref.samples[..., i:i + 1], use)
                    cells.append(make_cell(table, row, f"{ENCODER_LABEL[encoder]} / {c}", kl,
                                           floor[c], float(ref.ess.median()), use))
    return cells, floors
