"""The layout docs/ARCHITECTURE.md declares, checked on the code: its layering list against every
import of pipeline/ and flows/ (read from the AST by bench/architecture.py), and the engine's
module and folder sizes. A second: no run, no torch."""
from __future__ import annotations

from bench.architecture import (FORECAST_LINES, MAX_ANY, MAX_LINES, MAX_MODULES, any_uses,
                                imports, sizes)

ENGINE = ("panels", "members", "combine", "backtest", "nowcast", "evaluation", "outputs")


def test_no_import_runs_back_up_the_declared_layers_and_no_cycle():
    """Type-only imports included: the weekly report, which reads the weekly run's results,
    is the weekly run's (pipeline/forecast/report/), not the generic report's."""
    found = imports()
    assert found["upward_imports"] == []
    assert found["upward_type_checking_imports"] == []
    assert found["package_cycles"] == []
    assert found["module_cycles"] == []
    assert found["type_checking_imports"] > 0          # they are counted, not skipped
    # the pipeline/ library never imports flows/ (Prefect) at all
    assert not any(target.startswith("flows") for source, targets in
                   found["package_graph"].items() if source.startswith("pipeline")
                   for target in targets)


def test_the_engine_has_no_module_over_400_lines_and_no_folder_over_10_modules():
    found = sizes()
    engine = [path for path in found["lines"] if path.split("/")[1] in ENGINE]
    assert len(engine) > 40      # every engine module is counted
    assert [p for p in engine if found["lines"][p] > MAX_LINES] == []
    assert {folder: n for folder, n in found["over_max_modules"].items()
            if folder.split("/")[1] in ENGINE or folder.startswith("pipeline/data")} == {}
    assert max(len(found["folders"][f"pipeline/{p}"]) for p in ENGINE) <= MAX_MODULES


def test_the_weekly_run_and_the_flows_use_any_at_most_six_times():
    """Typed through: Protocols, TypedDicts and generics rather than ``Any`` (issue 37 counted
    14 words "Any" there, imports and a comment included: 8 uses; measured now: 2)."""
    found = any_uses()
    assert sum(found.values()) <= MAX_ANY, found
    assert found["pipeline/forecast/county_skill.py"] == 1   # the JSON summary it reads back


def test_the_weekly_runs_config_and_steps_are_split_under_300_lines():
    """config.py (347 lines) and steps.py (385) split by concept: the step settings
    (settings.py) and the published forecast (published_forecast.py) moved out."""
    lines = sizes()["lines"]
    split = ("config", "settings", "steps", "published_forecast")
    assert {m: lines[f"pipeline/forecast/{m}.py"] < FORECAST_LINES for m in split} == {
        m: True for m in split}
