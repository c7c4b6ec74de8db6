"""What the online interval calibration costs in WIS, on every panel →
``bench/results/calibration.json`` (key ``calibration_cost``).

The cost is the published forecast's WIS over the same average's before the calibration (the
backtests score both at every cell: ``published`` and ``ensemble-uncalibrated`` in
``backtest.json`` and ``backtest_counties.json``, ``published`` and ``uncalibrated`` in
``nhsn.json``): Σ WIS over every scored cell and horizon, published ÷ uncalibrated. Below 1 the
calibration helps; the bound is 1.01. This script computes nothing from forecasts: it reads the
four backtests' results, written by their own commands (named beside each figure), so a figure
here is as fresh as its backtest.

    python -m bench.calibration_cost
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
BOUND = 1.01
# panel -> (results file, how it is read)
PANELS = {"sf": "backtest.json", "counties": "backtest_counties.json",
          "nhsn": "nhsn.json", "nhsn_ed": "nhsn.json"}


def backtest_cost(results: dict[str, Any], target: str) -> float:
    """Σ over horizons of the mean WIS (the same cells at every horizon), published ÷
    uncalibrated."""
    scored = results["by_target"][target]
    published = sum(scored["published"]["mean_wis"].values())
    uncalibrated = sum(scored["ensemble-uncalibrated"]["mean_wis"].values())
    return float(published / uncalibrated)


def panel_costs() -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for panel in ("sf", "counties"):
        results = json.loads((RESULTS / PANELS[panel]).read_text())
        out[panel] = {"by_target": {t: backtest_cost(results, t) for t in ("cases", "I")},
                      "source": f"bench/results/{PANELS[panel]} ({results.get('command')})"}
        out[panel]["value"] = max(out[panel]["by_target"].values())
    hub = json.loads((RESULTS / "nhsn.json").read_text())
    out["nhsn"] = {"value": float(hub["calibration_cost"]),
                   "source": f"bench/results/nhsn.json ({hub.get('command')})"}
    out["nhsn_ed"] = {"value": float(hub["ed_visits"]["calibration_cost"]),
                      "source": "bench/results/nhsn.json, ed_visits"}
    for figures in out.values():
        figures["within_bound"] = figures["value"] <= BOUND
    return out


def main() -> int:
    from pipeline.io import atomic_write_json

    costs = panel_costs()
    path = RESULTS / "calibration.json"
    current = json.loads(path.read_text()) if path.is_file() else {}
    current["calibration_cost"] = {"bound": BOUND, "panels": costs,
                                   "command": "python -m bench.calibration_cost",
                                   **{p: f["value"] for p, f in costs.items()}}
    atomic_write_json(path, current)
    for panel, figures in costs.items():
        detail = ", ".join(f"{t} {v:.4f}" for t, v in figures.get("by_target", {}).items())
        print(f"{panel:9s} {figures['value']:.4f}{' (' + detail + ')' if detail else ''}"
              f"{'' if figures['within_bound'] else '  > ' + str(BOUND)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
