"""Train the paper's model variants in parallel on a Dask cluster (prefect-dask).

    python -m flows.scale_out                                   # local cluster (2 workers)
    python -m flows.scale_out --address tcp://scheduler:8786    # an existing Dask cluster
    python -m flows.scale_out --preset tiny --variants mlp transformer

Variants (paper, Tables 3–5): transformer, transformer + kinetic-energy loss, Mamba. Each is a
task that simulates the training data and trains (or reuses) the forward/backward joint models;
the tasks go to ``DaskTaskRunner`` so they run on separate Dask workers. With ``--address`` the
runner connects to the given scheduler instead of starting a ``LocalCluster``; every worker then
needs this package installed and the same ``FLOWCAST_DATA_DIR`` (shared filesystem) so the model
cache is shared. The flow returns each variant's model key and best validation NLL.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Any, TypedDict, cast

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import PrefectFuture
from prefect.task_runners import TaskRunner
from prefect_dask.task_runners import DaskTaskRunner

from pipeline import forecast as fc
from pipeline.names import Direction
from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models

# The paper's variants (Table 5 rows) as (name, encoder choice of pipeline.training.presets); the
# "transformer-ke" preset trains the transformer with the kinetic-energy terms.
PAPER_VARIANTS: dict[str, str] = {"transformer": "transformer",
                                  "transformer-ke": "transformer-ke", "mamba": "mamba",
                                  "mlp": "mlp"}


class VariantResult(TypedDict):
    variant: str
    model_key: str
    reused: bool
    best_val_nll: dict[Direction, float]


@task(name="train-variant", cache_policy=NO_CACHE, persist_result=False)
def train_variant(config: fc.ForecastConfig, variant: str, retrain: bool) -> VariantResult:
    import torch

    torch.set_num_threads(1)  # one core per Dask worker; several variants share the machine
    data = simulate_training_data(config)
    models = train_or_reuse_models(config, data, retrain=retrain)
    return {"variant": variant, "model_key": models.key, "reused": models.reused,
            "best_val_nll": models.best_val_nll}


def task_runner(address: str | None, n_workers: int) -> DaskTaskRunner:
    if address:
        return DaskTaskRunner(address=address)
    return DaskTaskRunner(cluster_kwargs={"n_workers": n_workers, "threads_per_worker": 1,
                                          "processes": True})


@flow(name="train_variants")
def train_variants(preset: str = "default", variants: list[str] | None = None, seed: int = 0,
                   retrain: bool = False) -> list[VariantResult]:
    logger = get_run_logger()
    names = variants or list(PAPER_VARIANTS)
    unknown = [v for v in names if v not in PAPER_VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; known: {sorted(PAPER_VARIANTS)}")
    futures = [train_variant.submit(fc.resolve_config(preset, seed=seed, encoder=PAPER_VARIANTS[v]),
                                    v, retrain) for v in names]
    results = [f.result() for f in futures]
    for r in results:
        logger.info("%s: model %s… (%s) best val NLL fw %.3f bw %.3f", r["variant"],
                    r["model_key"][:12], "reused" if r["reused"] else "trained",
                    r["best_val_nll"]["forward"], r["best_val_nll"]["backward"])
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flows.scale_out", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="default", choices=tuple(fc.FORECAST_PRESETS))
    parser.add_argument("--variants", nargs="*", default=None, choices=tuple(PAPER_VARIANTS))
    parser.add_argument("--address", default=None, help="existing Dask scheduler address")
    parser.add_argument("--workers", type=int, default=2, help="local cluster size")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--retrain", action="store_true")
    args = parser.parse_args(argv)
    # DaskTaskRunner subclasses the bare TaskRunner (so its future type defaults to
    # PrefectConcurrentFuture) while Flow.with_options wants the invariant
    # TaskRunner[PrefectFuture[Any]]; prefect's own annotations can't express the subclass.
    runner = cast("TaskRunner[PrefectFuture[Any]]", task_runner(args.address, args.workers))
    runner_flow = train_variants.with_options(task_runner=runner)
    for r in runner_flow(preset=args.preset, variants=args.variants, seed=args.seed,
                         retrain=args.retrain):
        print(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
