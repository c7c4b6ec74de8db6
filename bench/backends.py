"""nflows vs zuko MAF backend: accuracy and speed on the same conditional toy problem.

Problem (known density): context c ~ U(-2, 2)^2, target x | c ~ N(mu(c), L(c) L(c)^T) in 3-D with
mu(c) = (sin 2c1, c1 c2 / 2, cos c2), L(c) lower triangular with diagonal
(exp(0.4 c1), 0.5, exp(-0.4 c2)) and below-diagonal entries (0.8 tanh c1, 0.5, -0.6 c2 / 2).
The oracle NLL (the conditional entropy estimated on the test set) is the floor both flows
approach. Both backends get the same architecture (FlowConfig: 10 layers, hidden 6, the paper's
SIR sizes), the same initial seed, the same batches (Adam, lr 1e-3, batch 2048) and the same
number of steps; we report the held-out NLL, the ms per training step, the time to draw
1000 samples for each of 100 contexts, and whether any sample was non-finite.

Run ``python bench/backends.py --quick`` for a smoke-sized run (tiny sizes, seconds); the full
run is meant to be run alone on the machine. Writes bench/results/backends.json.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from pipeline.io import atomic_write_json
from pipeline.models.maf import BACKENDS, FlowConfig, build_flow

RESULTS = Path(__file__).resolve().parent / "results" / "backends.json"


@dataclass(frozen=True)
class BenchSizes:
    steps: int
    batch_size: int
    test_points: int
    sample_contexts: int
    samples_per_context: int
    layers: int = 10
    hidden_features: int = 6


FULL = BenchSizes(steps=2000, batch_size=2048, test_points=20000, sample_contexts=100,
                  samples_per_context=1000)
QUICK = BenchSizes(steps=60, batch_size=256, test_points=2000, sample_contexts=20,
                   samples_per_context=200)


def toy_problem(n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(context (n, 2), target (n, 3), true log density (n,))."""
    c = 4 * torch.rand(n, 2, generator=generator) - 2
    c1, c2 = c[:, 0], c[:, 1]
    mean = torch.stack([torch.sin(2 * c1), c1 * c2 / 2, torch.cos(c2)], dim=1)
    scale_tril = torch.zeros(n, 3, 3)
    scale_tril[:, 0, 0] = torch.exp(0.4 * c1)
    scale_tril[:, 1, 1] = 0.5
    scale_tril[:, 2, 2] = torch.exp(-0.4 * c2)
    scale_tril[:, 1, 0] = 0.8 * torch.tanh(c1)
    scale_tril[:, 2, 0] = 0.5
    scale_tril[:, 2, 1] = -0.3 * c2
    eps = torch.randn(n, 3, generator=generator)
    target = mean + torch.einsum("nij,nj->ni", scale_tril, eps)
    density = torch.distributions.MultivariateNormal(mean, scale_tril=scale_tril)
    return c, target, density.log_prob(target)


def bench_backend(backend: str, sizes: BenchSizes, seed: int) -> dict[str, float | bool]:
    torch.manual_seed(seed)
    flow = build_flow(FlowConfig(3, 2, layers=sizes.layers, hidden_features=sizes.hidden_features,
                                 backend=backend))  # type: ignore[arg-type]
    optimizer = torch.optim.Adam(flow.parameters(), lr=1e-3)
    data = torch.Generator().manual_seed(seed)
    step_ms = []
    for _ in range(sizes.steps):
        context, target, _ = toy_problem(sizes.batch_size, data)
        start = time.perf_counter()
        loss = -flow.log_prob(target, context).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step_ms.append(1000 * (time.perf_counter() - start))
    test_context, test_target, true_log_prob = toy_problem(sizes.test_points,
                                                           torch.Generator().manual_seed(seed + 1))
    with torch.no_grad():
        nll = -float(flow.log_prob(test_target, test_context).mean())
        contexts = test_context[: sizes.sample_contexts]
        start = time.perf_counter()
        samples = flow.sample(sizes.samples_per_context, contexts, torch.Generator().manual_seed(0))
        sample_seconds = time.perf_counter() - start
    return {"heldout_nll": nll, "oracle_nll": -float(true_log_prob.mean()),
            "ms_per_step_median": statistics.median(step_ms[len(step_ms) // 5:]),
            "sample_seconds": sample_seconds,
            "samples_finite": bool(torch.isfinite(samples).all()),
            "max_abs_sample": float(samples.abs().max())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    sizes = QUICK if args.quick else FULL
    results = {backend: bench_backend(backend, sizes, args.seed) for backend in BACKENDS}
    faster = min(BACKENDS, key=lambda b: results[b]["ms_per_step_median"])
    payload = {"quick": args.quick, "sizes": asdict(sizes), "threads": args.threads,
               "seed": args.seed, "torch": torch.__version__, "python": platform.python_version(),
               "results": results, "faster_training_backend": faster,
               "speedup_zuko_over_nflows": results["nflows"]["ms_per_step_median"]
               / results["zuko"]["ms_per_step_median"]}
    atomic_write_json(args.out, payload)
    for backend, row in results.items():
        print(f"{backend:7s} NLL {row['heldout_nll']:.3f} (oracle {row['oracle_nll']:.3f})  "
              f"{row['ms_per_step_median']:.1f} ms/step  sampling {row['sample_seconds']:.3f} s  "
              f"finite={row['samples_finite']}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
