"""The paper's Tables 1–4 (mean KL divergences) recomputed beside the paper's numbers.

``flowcast reproduce tables`` and ``python -m bench.paper_tables`` run it. A run trains (or loads
from ``Locations.work``) the 19 models the tables need (:mod:`pipeline.paper.models`), computes
every cell (:mod:`~pipeline.paper.vehicle_tables`: Tables 1–2, :mod:`~pipeline.paper.sir_tables`:
Tables 3–4) and writes ``paper_tables.{json,md}`` plus confidence-region figures to
``Locations.results`` (:mod:`~pipeline.paper.tables`). The protocol is
:data:`pipeline.paper.config.PROTOCOL` (stored in the JSON); docs/estimation.md discusses it.
"""
from __future__ import annotations

from pipeline.paper.cells import Cell
from pipeline.paper.config import PROTOCOL, BenchConfig, Locations
from pipeline.paper.models import RequiredModel, pretrain, required_models, trained_estimator
from pipeline.paper.render import render_markdown
from pipeline.paper.tables import TablesResult, run

__all__ = ["PROTOCOL", "BenchConfig", "Cell", "Locations", "RequiredModel", "TablesResult",
           "pretrain", "render_markdown", "required_models", "run", "trained_estimator"]
