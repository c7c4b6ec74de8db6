"""paper_tables.md: every table's cells beside the paper's values, the floors and the ESS."""
from __future__ import annotations

from collections.abc import Sequence

from pipeline.paper.cells import Cell
from pipeline.paper.config import BenchConfig
from pipeline.paper.published import PAPER


def render_markdown(cells: Sequence[Cell], cfg: BenchConfig, seconds: float) -> str:
    lines = ["# Paper Tables 1–4: mean KL divergence, paper vs ours", "",
             f"Run: {'QUICK (tiny sizes, not comparable)' if cfg.quick else 'full'}; "
             f"{seconds:.0f} s. KL = D(estimate ‖ reference posterior), k-NN (k = 1), "
             f"{cfg.n_samples} vs {cfg.n_samples} samples. *floor* = KL between two independent "
             "reference samples (what 0 looks like); *ESS* = median effective sample size of "
             "the reference's likelihood weights. Protocol: docs/estimation.md.", ""]
    for table in PAPER:
        lines += [f"## {table}", "", "| row | column | paper | ours | floor | ours − floor | "
                  "ESS | windows |", "|---|---|---:|---:|---:|---:|---:|---:|"]
        for c in (c for c in cells if c["table"] == table):
            lines.append(f"| {c['row']} | {c['col']} | {c['paper']:.3f} | {c['ours']:.3f} | "
                         f"{c['floor']:.3f} | {c['ours'] - c['floor']:.3f} | {c['ess_median']:.0f} "
                         f"| {c['windows_used']}/{c['windows']} |")
        collapsed = [c for c in cells if c["table"] == table and c.get("collapsed_windows")]
        lines += [f"*{c['row']} / {c['col']}: {c.get('collapsed_windows')} windows where the "
                  "particle set collapsed onto a single point (KL = +inf) are excluded from the "
                  "mean.*" for c in collapsed]
        lines.append("")
    better = sum(c["ours"] <= c["paper"] for c in cells)
    lines.append(f"{better} of {len(cells)} cells at or below the paper's value.")
    return "\n".join(lines) + "\n"
