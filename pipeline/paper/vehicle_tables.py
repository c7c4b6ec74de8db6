"""Tables 1 and 2: the vehicle, at three locations around the bifurcation (t = 5.5).

Table 1: fixed-step data (``vehicle-full``), forward, the transformer model against a bootstrap
particle filter. Table 2: dropout data (``vehicle-dropout``), the three encoders, forward and
backward, plus one confidence-region figure per encoder and direction.
"""
from __future__ import annotations

import torch
from torch import Tensor

from pipeline.inference.estimate import assemble_context, confidence_regions, uses_absolute_time
from pipeline.inference.reference import (ReferencePosterior, simulate_vehicle_candidates,
                                          vehicle_reference)
from pipeline.models.estimator import ConditionalEstimator
from pipeline.paper.cells import Cell, collapsed_windows, make_cell, mean_kl, usable_windows
from pipeline.paper.config import (DIR_LABEL, ENCODER_LABEL, ENCODERS, LOCATION_LABEL, LOCATIONS,
                                   VEHICLE_DROPOUT_TARGETS, VEHICLE_FULL_TARGETS, BenchConfig,
                                   Locations)
from pipeline.paper.models import RequiredModel, model_samples, trained_estimator
from pipeline.systems.vehicle import VehicleConfig
from pipeline.names import DIRECTIONS

# (values (B, R, 2), context times (B, R), target times (B,))
Windows = tuple[Tensor, Tensor, Tensor]


def vehicle_windows(config: VehicleConfig, direction: str, target_time: float, n: int,
                    seed: int) -> Windows:
    """B test windows (values (B,5,2), context times (B,5), target times (B,)), fresh vehicles."""
    from pipeline.systems.vehicle import simulate_vehicle

    ens = simulate_vehicle(config, n=n * 3, seed=seed, dtype=torch.float64)
    times = ens.times
    values: list[Tensor] = []
    ctx_times: list[Tensor] = []
    targets: list[Tensor] = []
    for i in range(ens.n_trajectories):
        kept = torch.nonzero(ens.kept[i]).flatten()
        if direction == "forward":
            ok = kept[5:]
        else:
            ok = kept[:-5] if len(kept) > 5 else kept[:0]
        if len(ok) == 0:
            continue
        j = int(ok[torch.argmin((times[ok] - target_time).abs())])
        pos = int(torch.nonzero(kept == j)[0])
        idx = kept[pos - 5:pos] if direction == "forward" else kept[pos + 1:pos + 6]
        values.append(ens.observations[i, idx])
        ctx_times.append(times[idx])
        targets.append(times[j])
        if len(targets) == n:
            break
    return torch.stack(values), torch.stack(ctx_times), torch.stack(targets)


def smc_vehicle_samples(config: VehicleConfig, values: Tensor, ctx_times: Tensor,
                        n_particles: int, seed: int) -> Tensor:
    """Table 1's SMC: prior around o_n, 4 update steps, one step without update (protocol).

    The paper's prior p(o_n) says nothing of the unobserved heading, steering and speed; they
    are drawn from the simulator's own vehicles at t_n (both ψ branches), the prior the
    reference posterior uses too, so the baseline starts from the same knowledge of them."""
    from pipeline.inference.smc import SMCConfig, run_filter
    from pipeline.inference.smc_models import VehicleModel
    from pipeline.systems.vehicle import simulate_vehicle

    b = values.shape[0]
    index = torch.round(ctx_times[:, 0] / config.dt).long()
    vehicles = simulate_vehicle(config, n=n_particles, seed=seed + 1, dtype=torch.float64)
    hidden = vehicles.states[:, index, 2:].transpose(0, 1)                # (B, N, 3) θ, φ, v
    # ψ as the model keeps it: 0 ("not drawn yet") before the switch, the vehicle's own after.
    switched = ctx_times[:, :1] >= config.switch_time
    psi = torch.where(switched, vehicles.psi.double()[None, :], 0.0)       # (B, N)
    gen = torch.Generator().manual_seed(seed + 2)
    positions = values[:, :1].double() + config.obs_sigma * torch.randn(
        (b, n_particles, 2), generator=gen, dtype=torch.float64)
    initial = torch.cat([positions, hidden, psi[..., None]], dim=-1)
    model = VehicleModel.create(config)  # dynamics and likelihood; the prior is ``initial``
    step = float(ctx_times[0, 1] - ctx_times[0, 0])
    grid = torch.arange(6, dtype=torch.float64) * step                  # relative times
    # o_n built the prior; weighting by it again would count it twice, so step 0 has no update
    # and the four updates use o_{n+1} … o_{n+4}, as the paper's p(x_{n+4} | o_{n+1..n+4}).
    no_update = torch.full((b, 1, 2), float("nan"), dtype=torch.float64)
    obs = torch.cat([no_update, values[:, 1:].double(), no_update], dim=1)
    # Filters share one time axis: all windows of a location start at the same grid time here.
    result = run_filter(model, obs, SMCConfig(num_particles=n_particles, seed=seed, quantiles=()),
                        times=grid + float(ctx_times[0, 0]), initial_particles=initial)
    idx = torch.multinomial(result.log_weights.exp(), n_particles, replacement=True, generator=gen)
    return torch.gather(result.particles[..., :2], 1, idx[..., None].expand(-1, -1, 2))


def vehicle_cells(cfg: BenchConfig, locations: Locations,
                  figures: list[str]) -> tuple[list[Cell], dict[str, float]]:
    """The cells of Tables 1 and 2 and their KL floors; appends the figures' paths."""
    from pipeline.systems.vehicle import get_vehicle_config

    cells: list[Cell] = []
    floors: dict[str, float] = {}
    n = cfg.n_samples
    # ---- Table 1: vehicle-full, forward, transformer vs SMC
    full = get_vehicle_config("vehicle-full")
    cand_a = simulate_vehicle_candidates(full, cfg.vehicle_candidates, seed=101)
    cand_b = simulate_vehicle_candidates(full, cfg.vehicle_candidates, seed=202)
    est = trained_estimator(RequiredModel("vehicle", "transformer", "forward", "vehicle-full"),
                            cfg, locations)
    for loc in LOCATIONS:
        t_target = VEHICLE_FULL_TARGETS["forward"][loc]
        values, ctx_t, tgt = vehicle_windows(full, "forward", t_target, cfg.n_vehicle_windows,
                                             seed=5000 + LOCATIONS.index(loc))
        ref = vehicle_reference(cand_a, ctx_t, values, tgt, n, seed=1)
        ref_b = vehicle_reference(cand_b, ctx_t, values, tgt, n, seed=2)
        use = usable_windows(ref, ref_b)
        floor = mean_kl(ref.samples, ref_b.samples, use)
        nf = mean_kl(model_samples(est, values, ctx_t, tgt, n, seed=3), ref.samples, use)
        smc_samples = smc_vehicle_samples(full, values, ctx_t, n, seed=4)
        collapsed = collapsed_windows(smc_samples) & use
        smc = mean_kl(smc_samples, ref.samples, use & ~collapsed)
        row = f"{LOCATION_LABEL[loc]} (fw)"
        ess = float(ref.ess.median())
        smc_cell = make_cell("Table 1", row, "Sequential MC", smc, floor, ess, use & ~collapsed)
        # A particle set collapsed onto one point has KL = +inf against a continuous reference;
        # it is counted here instead of being averaged in (or hidden by jitter).
        smc_cell["collapsed_windows"] = int(collapsed.sum())
        cells += [make_cell("Table 1", row, "Conditional NF", nf, floor, ess, use), smc_cell]
        floors[f"Table 1 / {row}"] = floor
    # ---- Table 2: vehicle-dropout, 3 encoders × fw/bw
    drop = get_vehicle_config("vehicle-dropout")
    cand_a = simulate_vehicle_candidates(drop, cfg.vehicle_candidates, seed=303)
    cand_b = simulate_vehicle_candidates(drop, cfg.vehicle_candidates, seed=404)
    for direction in DIRECTIONS:
        windows = {loc: vehicle_windows(drop, direction, VEHICLE_DROPOUT_TARGETS[direction][loc],
                                        cfg.n_vehicle_windows, seed=6000 + LOCATIONS.index(loc))
                   for loc in LOCATIONS}
        refs = {loc: vehicle_reference(cand_a, w[1], w[0], w[2], n, seed=1)
                for loc, w in windows.items()}
        usable: dict[str, Tensor] = {}
        for loc, (values, ctx_t, tgt) in windows.items():
            ref_b = vehicle_reference(cand_b, ctx_t, values, tgt, n, seed=2)
            usable[loc] = usable_windows(refs[loc], ref_b)
            floors[f"Table 2 / {LOCATION_LABEL[loc]} ({DIR_LABEL[direction]})"] = \
                mean_kl(refs[loc].samples, ref_b.samples, usable[loc])
        for encoder in ENCODERS:
            est = trained_estimator(RequiredModel("vehicle", encoder, direction), cfg, locations)
            for loc, (values, ctx_t, tgt) in windows.items():
                row = f"{LOCATION_LABEL[loc]} ({DIR_LABEL[direction]})"
                kl = mean_kl(model_samples(est, values, ctx_t, tgt, n, seed=3),
                             refs[loc].samples, usable[loc])
                cells.append(make_cell("Table 2", row, ENCODER_LABEL[encoder], kl,
                                       floors[f"Table 2 / {row}"], float(refs[loc].ess.median()),
                                       usable[loc]))
            figures.append(region_figure(est, encoder, direction, windows, refs, locations))
    return cells, floors


def region_figure(est: ConditionalEstimator, encoder: str, direction: str,
                  windows: dict[str, Windows], refs: dict[str, ReferencePosterior],
                  locations: Locations) -> str:
    """1/2/3σ regions (pushed base circles) for the first window of each location; returns the
    figure's path (relative to ``locations.root``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for ax, loc in zip(axes, LOCATIONS, strict=True):
        values, ctx_t, tgt = (w[:1] for w in windows[loc])
        mask = torch.ones(ctx_t.shape, dtype=torch.bool)
        context = assemble_context(values.double(), ctx_t.double(), mask, tgt.double(),
                                   uses_absolute_time(est))
        samples = model_samples(est, values, ctx_t, tgt, 500, seed=9)[0]
        ref = refs[loc].samples[0]
        ax.scatter(ref[:, 0], ref[:, 1], s=3, c="0.6", label="reference posterior")
        ax.scatter(samples[:, 0], samples[:, 1], s=3, c="tab:blue", alpha=0.4, label="NF samples")
        for r, pts in zip((1, 2, 3), confidence_regions(est, context, mask), strict=True):
            closed = torch.cat([pts[0], pts[0, :1]]).detach()
            ax.plot(closed[:, 0], closed[:, 1], lw=1.2, label=f"{r}σ region")
        ax.plot(values[0, :, 0], values[0, :, 1], "k^", ms=5, label="context observations")
        ax.set_title(f"{LOCATION_LABEL[loc]} ({DIR_LABEL[direction]}), t = {float(tgt[0]):.1f}")
        ax.set_xlabel("p_x")
        ax.set_ylabel("p_y")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"Vehicle (dropout), {ENCODER_LABEL[encoder]}: confidence regions")
    fig.tight_layout()
    path = locations.results / "figures" / f"regions-vehicle-{encoder}-{direction}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return locations.display(path)
