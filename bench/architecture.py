"""The code's layout, measured from the code itself → bench/results/architecture.json.

(a) **Sizes**: lines per module and modules per folder under ``pipeline/`` (a folder's modules
    are its ``.py`` files other than ``__init__.py``); flagged: a module over 400 lines, a folder
    over 10 modules.
(b) **Imports**: every ``import`` statement of ``pipeline/`` and ``flows/`` read from the AST
    (top-level, function-local and ``if TYPE_CHECKING:`` ones alike), as a graph between the
    packages of the layering that ``docs/ARCHITECTURE.md`` declares (its numbered list under
    "## Layering", parsed here: a package may import its own layer and the layers listed before
    it). Listed: every import running back up (a lower layer importing a higher one; those under
    ``TYPE_CHECKING`` listed apart), every cycle between packages (strongly connected components
    of the package graph) and every cycle between modules, type-only imports included in both
    graphs (a type is a dependency too).
(c) **The weekly forecast's path**: one run of the weekly step on the ``tiny`` preset and the
    recorded DataSF exports (imported into a temporary ``FLOWCAST_DATA_DIR``, read offline, as
    ``tests/test_forecast_flow.py`` does) — the series from the cache, its S/I/R conversion, the
    nowcast step, the weekly forecast
    (:func:`pipeline.forecast.published_forecast.weekly_forecast`: panel, members, combiner,
    track record) and its hub file and tables — traced with ``sys.setprofile``.
    For every ``pipeline`` module: how many times control *enters* it from another module (a
    ``call`` event of one of its functions whose nearest calling ``pipeline``/``flows`` frame is
    in another module; library frames in between, e.g. torch calling a module's ``forward``, are
    looked through), and the loop-independent counts: its distinct entry functions, distinct
    entry edges (calling function → entered function) and calling modules. The joint models and
    the members' models are trained first, untraced (the path of a week whose models are
    stored); the forecast memo is then removed so that every member forecasts every cell; the
    NF-seeded SMC batch, which the weekly step forks into a child, is built in this process
    (``pipeline.forked``'s own fallback) so that its calls are counted too.

    python -m bench.architecture              # (a), (b) and (c)
    python -m bench.architecture --no-trace   # (a) and (b) only (a second)
"""
from __future__ import annotations

import argparse
import ast
import dis
import json
import os
import platform
import re
import shutil
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from pathlib import Path
from types import CodeType, FrameType
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
ARCHITECTURE_MD = ROOT / "docs" / "ARCHITECTURE.md"
SHARED_DATASF = ROOT.parent / "shared" / "data" / "datasf"
SHARED_CDPH = ROOT.parent / "shared" / "data" / "cdph"
MAX_LINES = 400
MAX_MODULES = 10
SCANNED = ("pipeline", "flows")
TOP_LEVEL = "pipeline"          # the package node of pipeline/'s own top-level modules
# where `Any` is counted (issue 37: at most 6 there) and where modules stay under FORECAST_LINES
ANY_SCANNED = ("pipeline/forecast", "flows")
MAX_ANY = 6
FORECAST_LINES = 300


# ---------------------------------------------------------------------------------- (a) sizes

def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def python_files(top: str) -> list[Path]:
    return sorted(p for p in (ROOT / top).rglob("*.py") if "__pycache__" not in p.parts)


def sizes() -> dict[str, Any]:
    files = python_files("pipeline")
    lines = {p.relative_to(ROOT).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
             for p in files}
    folders: dict[str, list[str]] = defaultdict(list)
    for p in files:
        if p.name != "__init__.py":
            folders[p.parent.relative_to(ROOT).as_posix()].append(p.name)
    for p in files:   # folders holding only __init__.py (e.g. pipeline/data) count 0 modules
        folders.setdefault(p.parent.relative_to(ROOT).as_posix(), [])
    longest = max(lines.items(), key=lambda kv: kv[1])
    fullest = max(folders.items(), key=lambda kv: len(kv[1]))
    return {
        "counted": "lines: physical lines of each .py file under pipeline/; modules of a folder: "
                   "its .py files other than __init__.py (subfolders not included)",
        "modules": len(files),
        "total_lines": sum(lines.values()),
        "max_lines": {"module": longest[0], "lines": longest[1]},
        "max_modules_per_folder": {"folder": fullest[0], "modules": len(fullest[1])},
        "over_max_lines": {k: v for k, v in sorted(lines.items(), key=lambda kv: -kv[1])
                           if v > MAX_LINES},
        "over_max_modules": {k: len(v) for k, v in sorted(folders.items()) if len(v) > MAX_MODULES},
        "lines": dict(sorted(lines.items())),
        "folders": {k: sorted(v) for k, v in sorted(folders.items())},
    }


def _any_in(node: ast.AST) -> int:
    """Uses of ``typing.Any`` in an expression, type strings (``cast("X[Any]", ...)``, quoted
    annotations) parsed as the expressions they are; prose strings never parse, so never count."""
    found = 0
    for sub in ast.walk(node):
        if isinstance(sub, ast.Name) and sub.id == "Any":
            found += 1
        elif isinstance(sub, ast.Attribute) and sub.attr == "Any":
            found += 1
        elif isinstance(sub, ast.Constant) and isinstance(sub.value, str) and "Any" in sub.value:
            try:
                found += _any_in(ast.parse(sub.value.strip(), mode="eval"))
            except SyntaxError:
                pass
    return found


def any_uses(tops: Iterable[str] = ANY_SCANNED) -> dict[str, int]:
    """Each module's uses of ``Any`` (imports not counted: an unused import is no use)."""
    files = [p for top in tops for p in (python_files(top) if (ROOT / top).is_dir()
                                         else [ROOT / top])]
    counts = {p.relative_to(ROOT).as_posix(): _any_in(ast.parse(p.read_text(encoding="utf-8")))
              for p in files}
    return {k: v for k, v in sorted(counts.items()) if v}


# -------------------------------------------------------------------------------- (b) imports

def declared_layers(text: str) -> list[list[str]]:
    """The numbered list under '## Layering' of ARCHITECTURE.md: each item's backticked package
    folders (``data/core/``) or modules (``names.py``), lowest layer first."""
    section = text.split("## Layering", 1)[1].split("\n## ", 1)[0]
    layers: list[list[str]] = []
    for line in section.splitlines():
        item = re.match(r"^\s*(\d+)\.\s+(.*)$", line)
        if item is None:
            continue
        lead = item.group(2).split(" — ", 1)[0]
        names = [n.strip("/") for n in re.findall(r"`([^`]+)`", lead)]
        layers.append([n.removeprefix("pipeline/") for n in names])
    if not layers:
        raise SystemExit(f"no numbered layering list under '## Layering' in {ARCHITECTURE_MD}")
    return layers


def layer_of_package(layers: list[list[str]]) -> dict[str, int]:
    """Package node → layer index. ``names.py``-style entries (pipeline's top-level modules)
    map to the node ``pipeline``; ``flows`` stays ``flows``; a folder to ``pipeline.<dotted>``."""
    out: dict[str, int] = {}
    for index, names in enumerate(layers):
        for name in names:
            if name.endswith(".py"):
                out[TOP_LEVEL] = index
            elif name == "flows":
                out["flows"] = index
            else:
                out[f"pipeline.{name.replace('/', '.')}"] = index
    return out


def package_of(module: str, packages: Iterable[str]) -> str | None:
    """The deepest declared package holding ``module`` (``pipeline.members.nf.flow`` →
    ``pipeline.members``); pipeline's own top-level modules → ``pipeline``."""
    best = None
    for package in packages:
        if package == TOP_LEVEL:
            continue
        if (module == package or module.startswith(package + ".")) and (
                best is None or len(package) > len(best)):
            best = package
    if best is None and (module == "pipeline" or (module.startswith("pipeline.")
                                                  and module.count(".") == 1)):
        return TOP_LEVEL
    return best


class _ImportVisitor(ast.NodeVisitor):
    """Every import statement with where it sits: module top level, a function, TYPE_CHECKING."""

    def __init__(self, module: str, is_package: bool) -> None:
        self.module, self.is_package = module, is_package
        self.found: list[dict[str, Any]] = []
        self._function = 0
        self._type_checking = 0

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        self._function += 1
        self.generic_visit(node)
        self._function -= 1

    visit_AsyncFunctionDef = visit_FunctionDef   # type: ignore[assignment]

    def visit_If(self, node: ast.If) -> None:
        test = node.test
        guarded = (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
            isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")
        if guarded:
            self._type_checking += 1
            for child in node.body:
                self.visit(child)
            self._type_checking -= 1
            for child in node.orelse:
                self.visit(child)
        else:
            self.generic_visit(node)

    def _add(self, target: str, line: int) -> None:
        self.found.append({"target": target, "line": line, "local": self._function > 0,
                           "type_checking": self._type_checking > 0})

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(alias.name, node.lineno)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            base = self.module.split(".")
            base = base if self.is_package else base[:-1]
            base = base[:len(base) - (node.level - 1)]
            parent = ".".join(base + ([node.module] if node.module else []))
        else:
            parent = node.module or ""
        for alias in node.names:
            self._add(f"{parent}.{alias.name}", node.lineno)


def resolve(target: str, known: set[str]) -> str | None:
    """``pipeline.report.checks`` (a module) or ``pipeline.report`` for ``from pipeline.report
    import FIGURE``: the longest known module prefix of the imported name."""
    parts = target.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in known:
            return candidate
    return None


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm (iterative): components of more than one node, or one with a loop."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            advanced = False
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                    advanced = True
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph.get(node, ()):
                    out.append(sorted(component))
    return sorted(out)


def imports() -> dict[str, Any]:
    layers = declared_layers(ARCHITECTURE_MD.read_text(encoding="utf-8"))
    layer = layer_of_package(layers)
    files = [p for top in SCANNED for p in python_files(top)]
    modules = {module_name(p): p for p in files}
    known = set(modules)
    unplaced = sorted({m for m in known if package_of(m, layer) is None})
    if unplaced:
        raise SystemExit(f"modules in no layer of {ARCHITECTURE_MD.name}'s list: {unplaced}")
    edges: list[dict[str, Any]] = []
    for module, path in modules.items():
        visitor = _ImportVisitor(module, path.name == "__init__.py")
        visitor.visit(ast.parse(path.read_text(encoding="utf-8"), str(path)))
        for found in visitor.found:
            target = resolve(found["target"], known)
            if target is None or target == module:
                continue
            edges.append({"from": module, "to": target, **found})
    package_graph: dict[str, set[str]] = defaultdict(set)
    module_graph: dict[str, set[str]] = defaultdict(set)
    upward, type_only_upward = [], []
    for edge in edges:
        source = package_of(edge["from"], layer)
        dest = package_of(edge["to"], layer)
        assert source is not None and dest is not None
        # a type-only import is a dependency too: cycles through one count
        module_graph[edge["from"]].add(edge["to"])
        if source != dest:
            package_graph[source].add(dest)
        if layer[dest] > layer[source]:
            row = {"from": f"{edge['from']}:{edge['line']}", "to": edge["to"],
                   "layers": f"{source} ({layer[source] + 1}) -> {dest} ({layer[dest] + 1})",
                   "function_local": edge["local"]}
            rows = type_only_upward if edge["type_checking"] else upward
            if row not in rows:         # one row per statement, not per imported name
                rows.append(row)
    return {
        "counted": "every import statement of pipeline/ and flows/ (module level, inside "
                   "functions, under TYPE_CHECKING), resolved to the longest known module; "
                   "a package is the deepest folder named in the layering list; an import runs "
                   "back up when the imported package's layer is listed after the importer's; "
                   "cycles are strongly connected components of the import graph, type-only "
                   "imports included",
        "layering": [[("pipeline/" + n) if n.endswith(".py") else n for n in names]
                     for names in layers],
        "packages": len({package_of(m, layer) for m in known}),
        "import_statements": len(edges),
        "function_local_imports": sum(e["local"] for e in edges),
        "type_checking_imports": sum(e["type_checking"] for e in edges),
        "upward_imports": upward,
        "upward_type_checking_imports": type_only_upward,
        "package_cycles": strongly_connected(package_graph),
        "module_cycles": strongly_connected(module_graph),
        "package_graph": {k: sorted(v) for k, v in sorted(package_graph.items())},
    }


# ----------------------------------------------------------------------------- (c) the path

_GENERATOR_FLAGS = 0x20 | 0x80 | 0x200   # CO_GENERATOR | CO_COROUTINE | CO_ASYNC_GENERATOR


class EntryCounter:
    """``sys.setprofile`` hook: per pipeline module, the call events entering it from another
    module (a generator's resumptions are not new entries: only its first activation counts)."""

    def __init__(self) -> None:
        self._module_of_file: dict[str, str | None] = {}
        self._first_resume: dict[CodeType, int] = {}
        self.entries: Counter[str] = Counter()
        self.edges: Counter[tuple[str, str, str, str]] = Counter()
        self.from_outside: Counter[str] = Counter()
        self.calls = 0

    def module_of(self, filename: str) -> str | None:
        found = self._module_of_file.get(filename, "")
        if found != "":
            return found
        path = Path(filename)
        module = None
        if path.is_absolute() and path.suffix == ".py":
            try:
                relative = path.resolve().relative_to(ROOT)
            except ValueError:
                relative = None
            if relative is not None and relative.parts[0] in ("pipeline", "flows", "bench"):
                module = module_name(ROOT / relative)
        self._module_of_file[filename] = module
        return module

    def _resumed(self, frame: FrameType) -> bool:
        code = frame.f_code
        if not code.co_flags & _GENERATOR_FLAGS:
            return False
        first = self._first_resume.get(code)
        if first is None:
            first = next(i.offset for i in dis.get_instructions(code) if i.opname == "RESUME")
            self._first_resume[code] = first
        return frame.f_lasti > first

    def __call__(self, frame: FrameType, event: str, arg: object) -> None:
        if event != "call":
            return
        module = self.module_of(frame.f_code.co_filename)
        if module is None or not module.startswith(("pipeline", "flows")):
            return
        if self._resumed(frame):
            return
        self.calls += 1
        caller = frame.f_back
        while caller is not None and self.module_of(caller.f_code.co_filename) is None:
            caller = caller.f_back        # look through library frames (torch, pandas, ...)
        source = None if caller is None else self.module_of(caller.f_code.co_filename)
        if source == module:
            return
        function = frame.f_code.co_qualname
        if source is None or source.startswith("bench"):
            self.from_outside[f"{module}.{function}"] += 1
            return
        assert caller is not None
        self.entries[module] += 1
        self.edges[(source, caller.f_code.co_qualname, module, function)] += 1

    def packages(self, layer: dict[str, int]) -> dict[str, dict[str, int]]:
        """The same, a package at a time: call events entering a package from another one."""
        entries: Counter[str] = Counter()
        edges: Counter[str] = Counter()
        for (source, _, module, _), count in self.edges.items():
            source_package, package = package_of(source, layer), package_of(module, layer)
            if source_package != package and package is not None:
                entries[package] += count
                edges[package] += 1
        return {p: {"entries": entries[p], "entry_edges": edges[p]}
                for p in sorted(entries, key=lambda p: (layer[p], p))}

    def summary(self, top: int = 12) -> dict[str, Any]:
        entry_functions: dict[str, set[str]] = defaultdict(set)
        callers: dict[str, set[str]] = defaultdict(set)
        edge_count: Counter[str] = Counter()
        for (source, _, module, function) in self.edges:
            entry_functions[module].add(function)
            callers[module].add(source)
            edge_count[module] += 1
        per_module = {m: {"entries": self.entries[m], "entry_edges": edge_count[m],
                          "entry_functions": len(entry_functions[m]),
                          "calling_modules": sorted(callers[m])}
                      for m in sorted(self.entries)}

        def most(key: str) -> list[dict[str, Any]]:
            ranked = sorted(per_module.items(), key=lambda kv: (-kv[1][key], kv[0]))[:top]
            return [{"module": m, **{k: v for k, v in row.items() if k != "calling_modules"},
                     "calling_modules": len(row["calling_modules"])} for m, row in ranked]

        return {
            "modules_entered": len(per_module),
            "pipeline_calls": self.calls,
            "max_entries": most("entries")[0] if per_module else None,
            "max_entry_edges": most("entry_edges")[0] if per_module else None,
            "max_calling_modules": max(
                ({"module": m, "calling_modules": len(r["calling_modules"])}
                 for m, r in per_module.items()), key=lambda r: r["calling_modules"]),
            "most_entries": most("entries"),
            "most_entry_edges": most("entry_edges"),
            "entered_from_the_bench": dict(sorted(self.from_outside.items())),
            "per_module": per_module,
        }


def _prepared_run(data_dir: Path, datasf: Path, cdph: Path | None) -> tuple[Any, Any]:
    """Untraced: the exports imported into the cache (CDPH's vintages as ``make forecast``
    imports them, reviewed revisions accepted), the tiny preset's joint models trained, and one
    weekly step run to fit the delay model and train and store the members' models."""
    os.environ["FLOWCAST_DATA_DIR"] = str(data_dir)
    os.environ.pop("FLOWCAST_CDPH_ARCHIVE", None)
    import dataclasses

    from pipeline.data.california.cdph import find_vintage_files
    from pipeline.data.california.cdph_source import import_cdph_exports

    if cdph is not None:
        import_cdph_exports(find_vintage_files(cdph), accept_revisions=True)
    from pipeline.forecast.config import DataSourceConfig, resolve_config
    from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models
    from pipeline.forecast.sources import load_series, series_to_sir
    from pipeline.forecast.nowcasting import nowcast_recent_days
    from pipeline.forecast.published_forecast import weekly_forecast

    config = resolve_config("tiny", data=dataclasses.replace(
        resolve_config("tiny").data, kind="import", import_paths=(str(datasf),)))
    series = load_series(config.data)
    recent = nowcast_recent_days(series, series_to_sir(series), config.nowcast,
                                 config.step_seed("nowcast"), None)
    models = train_or_reuse_models(config, simulate_training_data(config))
    weekly_forecast(recent, models, config)
    cache_config = dataclasses.replace(config, data=DataSourceConfig(
        **{**dataclasses.asdict(config.data), "kind": "cache", "import_paths": ()}))
    return cache_config, models


def traced_path(datasf: Path, cdph: Path | None) -> dict[str, Any]:
    import pandas as pd
    import torch

    torch.set_num_threads(1)
    work = Path(tempfile.mkdtemp(prefix="flowcast-architecture-"))
    try:
        started = time.perf_counter()
        config, models = _prepared_run(work / "data", datasf, cdph)
        prepared_s = time.perf_counter() - started

        from pipeline import forked
        from pipeline.forecast import published_forecast as steps
        from pipeline.forecast.nowcasting import nowcast_recent_days
        from pipeline.forecast.publish import weekly_tables, write_submission
        from pipeline.forecast.sources import load_series, series_to_sir

        memo = steps.forecast_memo_path(config.data.place, config.data.folder)
        memo.unlink(missing_ok=True)          # every member forecasts every cell again

        def in_place(build: Callable[[], Any], timeout_s: float = forked.CHILD_TIMEOUT_S
                     ) -> forked.ChildBuild[Any]:
            return forked.ChildBuild(build, None, None, timeout_s)

        steps.start_in_child = in_place       # type: ignore[assignment]

        def week() -> tuple[Any, Any]:
            series = load_series(config.data)
            sir = series_to_sir(series)
            recent = nowcast_recent_days(series, sir, config.nowcast,
                                         config.step_seed("nowcast"), None)
            weekly = steps.weekly_forecast(recent, models, config)
            tables = weekly_tables(weekly)
            # the run's date as forecast.publish.submission_run_date has it (the data date)
            dropped = config.data.trailing_days + (
                config.nowcast.fallback_trailing_days if weekly.nowcast is None else 0)
            run_date = (pd.Timestamp(recent.sir_frame["date"].iloc[-1])
                        + pd.Timedelta(days=dropped)).date()
            submission = write_submission(weekly, work / "hub", run_date)
            return weekly, (tables, submission)

        counter = EntryCounter()
        started = time.perf_counter()
        sys.setprofile(counter)
        try:
            weekly, (tables, submission) = week()
        finally:
            sys.setprofile(None)
        traced_s = time.perf_counter() - started
        summary = counter.summary()
        summary["per_package"] = counter.packages(
            layer_of_package(declared_layers(ARCHITECTURE_MD.read_text(encoding="utf-8"))))
        return {
            "counted": "a call event of a function of a pipeline module whose nearest calling "
                       "pipeline frame (library frames looked through) is in another pipeline "
                       "module; a generator counts once (its first activation), not at every "
                       "resumption; entry_edges: distinct (calling module and function, entered "
                       "function) pairs; entry_functions: distinct functions entered from "
                       "outside the module; calling_modules: the modules they were entered from. "
                       "Calls into pipeline from the bench itself (the path's entry points) are "
                       "listed apart. Worker threads are not traced (offline, the path starts "
                       "none); the SMC batch runs in this process instead of a forked child.",
            "path": ["forecast.sources.load_series (cache)", "forecast.sources.series_to_sir",
                     "forecast.nowcasting.nowcast_recent_days",
                     "forecast.published_forecast.weekly_forecast",
                     "forecast.publish.weekly_tables", "forecast.publish.write_submission"],
            "preset": "tiny", "data": [str(datasf)] + ([str(cdph)] if cdph else []),
            "nowcast": weekly.nowcast is not None,
            "reference_places": len(weekly.result.panel.references),
            "origins": int(len(weekly.result.origins)),
            "published_origin": str(weekly.origin.date()),
            "hub_rows": int(len(tables["hub_forecast.csv"])),
            "prepare_seconds": round(prepared_s, 1),
            "traced_seconds": round(traced_s, 1),
            **summary,
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)


# ---------------------------------------------------------------------------------- the report

def _print(result: dict[str, Any]) -> None:
    s, i = result["sizes"], result["imports"]
    print(f"(a) {s['modules']} modules, {s['total_lines']} lines under pipeline/; longest "
          f"{s['max_lines']['module']} ({s['max_lines']['lines']} lines); fullest folder "
          f"{s['max_modules_per_folder']['folder']} ({s['max_modules_per_folder']['modules']} "
          "modules)")
    print(f"    over {MAX_LINES} lines: {len(s['over_max_lines'])}")
    for module, lines in s["over_max_lines"].items():
        print(f"      {lines:5d}  {module}")
    print(f"    folders over {MAX_MODULES} modules: {s['over_max_modules'] or 'none'}")
    uses = result["any_uses"]
    print(f"    Any in {', '.join(ANY_SCANNED)}: {sum(uses.values())} uses (at most {MAX_ANY}) "
          f"{uses}")
    print(f"(b) {i['import_statements']} imports ({i['function_local_imports']} function-local, "
          f"{i['type_checking_imports']} under TYPE_CHECKING) between {i['packages']} packages "
          f"in {len(i['layering'])} layers")
    print(f"    upward imports: {len(i['upward_imports'])}")
    for row in i["upward_imports"]:
        print(f"      {row['from']} -> {row['to']}  [{row['layers']}]")
    print(f"    upward under TYPE_CHECKING only: {len(i['upward_type_checking_imports'])}")
    for row in i["upward_type_checking_imports"]:
        print(f"      {row['from']} -> {row['to']}")
    print(f"    package cycles: {i['package_cycles'] or 'none'}; module cycles: "
          f"{i['module_cycles'] or 'none'}")
    t = result.get("weekly_path")
    if t is None:
        return
    print(f"(c) the weekly path ({t['preset']}, published origin {t['published_origin']}): "
          f"{t['pipeline_calls']} calls of pipeline functions, {t['modules_entered']} modules "
          f"entered from another; traced in {t['traced_seconds']} s")
    print("    most entered (entries = call events from another module; edges = distinct "
          "calling function -> entered function; fns = distinct entry functions)")
    for row in t["most_entries"]:
        print(f"      {row['entries']:7d} entries  {row['entry_edges']:3d} edges  "
              f"{row['entry_functions']:3d} fns  {row['calling_modules']:2d} callers  "
              f"{row['module']}")
    print("    per package (entries / distinct entry edges from another package):")
    print("      " + ", ".join(f"{p.removeprefix('pipeline.')} {r['entries']}/{r['entry_edges']}"
                             for p, r in t["per_package"].items()))
    print("    most entry edges:")
    for row in t["most_entry_edges"][:6]:
        print(f"      {row['entry_edges']:3d} edges  {row['entry_functions']:3d} fns  "
              f"{row['calling_modules']:2d} callers  {row['module']}")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--no-trace", action="store_true", help="sizes and imports only")
    parser.add_argument("--data", default=str(SHARED_DATASF), help="DataSF CSV exports")
    parser.add_argument("--cdph", default=str(SHARED_CDPH), help="CDPH county downloads (the "
                        "reference counties and the nowcast's delay model); '' for none")
    parser.add_argument("--out", default=str(RESULTS / "architecture.json"))
    args = parser.parse_args(argv)
    result: dict[str, Any] = {
        "command": "python -m bench.architecture" + (" --no-trace" if args.no_trace else ""),
        "python": platform.python_version(),
        "sizes": sizes(),
        "imports": imports(),
        "any_uses": any_uses(),
    }
    if not args.no_trace:
        result["weekly_path"] = traced_path(Path(args.data), Path(args.cdph) if args.cdph else None)
    from pipeline.io import atomic_write_text

    atomic_write_text(Path(args.out), json.dumps(result, indent=2) + "\n")
    _print(result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
