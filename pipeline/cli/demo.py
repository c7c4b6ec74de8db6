"""`flowcast demo ...`: small demonstrations (the kinetic-energy double-moon figure)."""
from __future__ import annotations

import json
from pathlib import Path

import typer

from pipeline.cli import app
from pipeline.cli.output_paths import output_dir

demo = typer.Typer(no_args_is_help=True, help="Small demonstrations of the methods.")
app.add_typer(demo, name="demo")


@demo.command("kinetic")
def kinetic(
    out: Path = typer.Option(..., "--out", help="Directory for kinetic_layers.png and "
                             "kinetic_demo.json."),
    iterations: int = typer.Option(3000, "--iterations", min=1, help="Adam steps per flow."),
    seed: int = typer.Option(0, "--seed", help="Seed of initialisation, batches and test points."),
    path_weight: float = typer.Option(0.1, "--path-weight", min=0.0,
                                      help="lambda2 of the kinetic (path-length) term."),
    prior_weight: float = typer.Option(0.0, "--prior-weight", min=0.0,
                                       help="lambda3 of the intermediate-layer prior term."),
    layers: int = typer.Option(6, "--layers", min=2, help="Flow layers L."),
    backend: str = typer.Option("zuko", "--backend", help="nflows or zuko."),
) -> None:
    """Train an unconditional MAF on two moons with and without the kinetic term; plot every
    layer's output and report path lengths and held-out NLL."""
    from pipeline.demos.kinetic import KineticDemoConfig, run_kinetic_demo
    from pipeline.errors import ConfigError
    from pipeline.models.maf.base import BACKENDS
    from pipeline.training.kinetic import KineticWeights
    from pipeline.progress import rich_progress

    if backend not in BACKENDS:  # the error FlowConfig would raise, before any training
        raise ConfigError(f"FlowConfig.backend={backend!r}: must be one of {BACKENDS}")
    try:
        output_dir(out)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=1) from None
    config = KineticDemoConfig(iterations=iterations, seed=seed, layers=layers, backend=backend,
                               kinetic=KineticWeights(1.0, path_weight, prior_weight))
    with rich_progress("kinetic demo (2 flows)", total=2 * iterations) as progress:
        result = run_kinetic_demo(config, out, progress)
    summary = {name: {key: result[name][key] for key in
                      ("heldout_nll", "path_length_total", "kinetic_sum")}
               for name in ("maximum_likelihood", "with_kinetic_term")}
    typer.echo(json.dumps(summary, indent=2))
    typer.echo(f"path length ratio (kinetic / plain): {result['path_length_ratio']:.3f}")
    typer.echo(f"wrote {out / 'kinetic_layers.png'} and {out / 'kinetic_demo.json'}")
