"""What the online interval calibration costs in WIS, on every panel →
``bench/results/calibration.json`` (keys ``calibration_cost``, ``calibration_cost_worst_window``,
``coverage_by_phase`` and ``plausibility``).

The cost is the published forecast's WIS over the same average's before the calibration (the
backtests score both at every cell: ``published`` and ``ensemble-uncalibrated`` in
``backtest.json`` and ``backtest_counties.json``, ``published`` and ``uncalibrated`` in
``nhsn.json``): Σ WIS over every scored cell and horizon, published ÷ uncalibrated. Below 1 the
calibration helps; the bound is 1.01. This script computes nothing from forecasts: it reads the
four backtests' results, written by their own commands (named beside each figure), so a figure
here is as fresh as its backtest. The same files give each panel's cost in its worst window of 15
consecutive origins (bound 1.03: a calibration must let go of a past surge) and the published
coverage per phase of the epidemic with its bootstrap interval.

    python -m bench.calibration_cost
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from collections.abc import Iterator
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


# each panel's results file and where in it the published forecast's cost by window and
# coverage by phase are (the backtests: per target; the hubs: per target file or section)
WINDOW_BOUND = 1.03
WINDOW_PANELS = {"sf": ("backtest.json", None, "cases"),
                 "counties": ("backtest_counties.json", None, "cases"),
                 "nhsn": ("nhsn.json", None, None), "nhsn_ed": ("nhsn.json", "ed_visits", None),
                 "flusight": ("flusight.json", None, None)}


def _sections() -> Iterator[tuple[str, dict[str, Any], str, str | None]]:
    """(panel, its results, where they are, its target in a backtest's file) of every panel
    whose results file exists."""
    for panel, (name, section, target) in WINDOW_PANELS.items():
        path = RESULTS / name
        if not path.is_file():
            continue
        results = json.loads(path.read_text())
        if section is not None:
            results = results.get(section) or {}
        yield panel, results, f"bench/results/{name}{', ' + section if section else ''}", target


def worst_windows() -> dict[str, dict[str, Any]]:
    """Each panel's calibration cost in its worst window of 15 consecutive origins (published
    WIS / the same average uncalibrated), as its backtest measured it; a panel whose results
    predate the figure is named, not guessed."""
    out: dict[str, dict[str, Any]] = {}
    for panel, results, source, target in _sections():
        cost = (results.get("calibration_cost", {}).get(target) if target is not None
                else results.get("calibration_cost_by_window"))
        if not isinstance(cost, dict) or cost.get("worst_window") is None:
            out[panel] = {"value": None, "source": source,
                          "why": "its results predate the figure: re-run its backtest"}
            continue
        variants = (results.get("calibration_cost_variants", {}).get(target, {})
                    if target is not None else results.get("calibration_cost_variants", {}))
        out[panel] = {"value": cost["worst_window"], "all": cost["all"],
                      "window": cost["worst_window_origins"],
                      "window_origins": cost["window_origins"], "n_windows": cost["n_windows"],
                      "source": source, "within_bound": cost["worst_window"] <= WINDOW_BOUND,
                      # the variants of the published members beside it: (all, worst window)
                      "variants": {name: {"all": v["all"], "worst_window": v["worst_window"]}
                                   for name, v in variants.items()}}
    return out


def coverage_by_phase() -> dict[str, dict[str, Any]]:
    """Each panel's published 50 % and outer coverage per phase (falling, flat, rising), with
    their bootstrap intervals, and whether the 50 % interval's holds 0.50."""
    out: dict[str, dict[str, Any]] = {}
    for panel, results, source, target in _sections():
        phases = (results.get("by_target", {}).get(target, {}).get("published", {})
                  .get("by_regime") if target is not None else results.get("by_phase"))
        if not phases:
            out[panel] = {"source": source, "why": "its results predate the figure"}
            continue
        out[panel] = {"source": source} | {
            phase: {k: v for k, v in figures.items() if k.startswith("coverage")}
            | {"n_scored": figures.get("n_scored"),
               "interval50_holds_half": _holds(figures.get("coverage50_interval"), 0.5)}
            for phase, figures in phases.items() if phase in ("falling", "flat", "rising")}
    return out


def plausibility() -> dict[str, dict[str, Any]]:
    """Each panel's published bound (pipeline.combine.plausibility: falls only) and the share
    of its published quantiles beyond it (0: held within it), beside the share of the same
    average unbounded and of each member, as its backtest measured them."""
    out: dict[str, dict[str, Any]] = {}
    for panel, results, source, target in _sections():
        figures = results.get("plausibility")
        if not figures or figures.get("bound") is None:
            out[panel] = {"value": None, "source": source,
                          "why": (figures or {}).get("why", "its results predate the figure: "
                                                     "re-run its backtest")}
            continue
        shares = figures["share_beyond"]
        out[panel] = {"value": shares.get("published"), "source": source,
                      "bound": figures["bound"], "cells_bounded": figures["cells_bounded"],
                      "share_beyond": shares}
    return out


def _holds(interval: list[float] | None, value: float) -> bool | None:
    return None if interval is None else bool(interval[0] <= value <= interval[1])


def main() -> int:
    from pipeline.io import atomic_write_json

    costs = panel_costs()
    windows = worst_windows()
    phases = coverage_by_phase()
    path = RESULTS / "calibration.json"
    current = json.loads(path.read_text()) if path.is_file() else {}
    current["calibration_cost"] = {"bound": BOUND, "panels": costs,
                                   "command": "python -m bench.calibration_cost",
                                   **{p: f["value"] for p, f in costs.items()}}
    current["calibration_cost_worst_window"] = {
        "bound": WINDOW_BOUND, "panels": windows, "command": "python -m bench.calibration_cost",
        **{p: f["value"] for p, f in windows.items()}}
    current["coverage_by_phase"] = {"panels": phases,
                                    "command": "python -m bench.calibration_cost"}
    bounded = plausibility()
    current["plausibility"] = {"panels": bounded, "command": "python -m bench.calibration_cost",
                               **{p: f["value"] for p, f in bounded.items()}}
    atomic_write_json(path, current)
    for panel, figures in costs.items():
        detail = ", ".join(f"{t} {v:.4f}" for t, v in figures.get("by_target", {}).items())
        print(f"{panel:9s} {figures['value']:.4f}{' (' + detail + ')' if detail else ''}"
              f"{'' if figures['within_bound'] else '  > ' + str(BOUND)}")
    for panel, figures in windows.items():
        value = figures["value"]
        print(f"{panel:9s} worst window of 15: " + (f"{value:.4f} {figures['window']}"
                                                     if value is not None else figures["why"]))
        for name, v in figures.get("variants", {}).items():
            if v["all"] is not None and v["worst_window"] is not None:
                print(f"{'':9s}   {name}: all {v['all']:.4f}, worst {v['worst_window']:.4f}")
    for panel, figures in bounded.items():
        print(f"{panel:9s} published quantiles beyond the bound: {figures['value']}")
    for panel, figures in phases.items():
        rising = figures.get("rising")
        print(f"{panel:9s} rising 50%: " + (f"{rising['coverage50']:.2f} "
                                             f"{rising['coverage50_interval']}" if rising
                                             else figures.get("why", "-")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
