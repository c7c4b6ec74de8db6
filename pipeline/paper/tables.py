"""One run of the paper tables: every cell of Tables 1–4, written as JSON and Markdown."""
from __future__ import annotations

import dataclasses
import time
from typing import TypedDict

import torch

from pipeline.io import atomic_write_json, atomic_write_text
from pipeline.paper.cells import Cell
from pipeline.paper.config import MIN_REFERENCE_ESS, PROTOCOL, BenchConfig, Locations
from pipeline.paper.published import PAPER
from pipeline.paper.render import render_markdown
from pipeline.paper.sir_tables import sir_cells
from pipeline.paper.vehicle_tables import vehicle_cells


class TablesResult(TypedDict):
    """The content of paper_tables.json."""

    cells: list[Cell]
    kl_floor: dict[str, float]
    protocol: str
    config: dict[str, object]
    figures: list[str]
    seconds: float
    cells_at_or_below_paper: int
    min_reference_ess: float
    torch_threads: int


def run(cfg: BenchConfig, locations: Locations) -> TablesResult:
    """Compute every cell (training missing models first, one at a time) and write
    ``paper_tables[_quick].{json,md}`` to ``locations.results``."""
    torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
    start = time.perf_counter()
    figures: list[str] = []
    print("vehicle tables ...", flush=True)
    v_cells, v_floors = vehicle_cells(cfg, locations, figures)
    print("SIR tables ...", flush=True)
    s_cells, s_floors = sir_cells(cfg, locations)
    cells = v_cells + s_cells
    seconds = time.perf_counter() - start
    expected = sum(len(t) for t in PAPER.values())
    if len(cells) != expected:
        raise AssertionError(f"{len(cells)} cells computed, the paper has {expected}")
    result: TablesResult = {
        "cells": cells, "kl_floor": {**v_floors, **s_floors}, "protocol": PROTOCOL,
        "config": dict(dataclasses.asdict(cfg)), "figures": figures,
        "seconds": round(seconds, 1),
        "cells_at_or_below_paper": sum(c["ours"] <= c["paper"] for c in cells),
        "min_reference_ess": MIN_REFERENCE_ESS, "torch_threads": torch.get_num_threads()}
    suffix = "_quick" if cfg.quick else ""
    atomic_write_json(locations.results / f"paper_tables{suffix}.json", result)
    atomic_write_text(locations.results / f"paper_tables{suffix}.md",
                      render_markdown(cells, cfg, seconds))
    return result
