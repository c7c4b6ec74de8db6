"""A plain ``pip install .`` runs and publishes a round (issue 49, item 5): every third-party
module that ``pipeline/`` and ``flows/`` import is a distribution declared in ``[project]
dependencies`` (not only in the ``dev`` extra), and every declared runtime dependency is imported
somewhere or is a pin another dependency needs. Static (ast), so it takes well under a second."""
from __future__ import annotations

import ast
import importlib.metadata as md
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIRST_PARTY = {"pipeline", "flows", "bench", "tests"}
# Declared though nothing of ours imports them: pins of a dependency's own requirements (the
# README says why: Prefect's server breaks at run time without them).
PINS = {"fastapi": "prefect", "sqlalchemy": "prefect"}


def _name(requirement: str) -> str:
    """The canonical distribution name of a PEP 508 requirement ('PyYAML>=6' -> 'pyyaml')."""
    match = re.match(r"[A-Za-z0-9._-]+", requirement)
    assert match, requirement
    return re.sub(r"[-_.]+", "-", match.group(0)).lower()


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _runtime_imports(tree: ast.AST) -> set[str]:
    """Top-level modules imported outside ``if TYPE_CHECKING:`` blocks (those never run)."""
    found: set[str] = set()
    stack = [tree]
    while stack:
        node = stack.pop()
        if _is_type_checking(node):
            assert isinstance(node, ast.If)
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
        stack.extend(ast.iter_child_nodes(node))
    return found


def imported_modules() -> dict[str, set[str]]:
    """Third-party top-level module -> the files of ``pipeline/`` and ``flows/`` importing it."""
    out: dict[str, set[str]] = {}
    for package in ("pipeline", "flows"):
        for path in (ROOT / package).rglob("*.py"):
            for module in _runtime_imports(ast.parse(path.read_text(encoding="utf-8"))):
                if module not in sys.stdlib_module_names and module not in FIRST_PARTY:
                    out.setdefault(module, set()).add(str(path.relative_to(ROOT)))
    return out


def declared() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    return {_name(r) for r in project["dependencies"]}


def test_every_imported_module_is_a_declared_runtime_dependency():
    distributions = md.packages_distributions()
    runtime = declared()
    modules = imported_modules()
    assert {"hubdata", "pandas", "torch", "prefect"} <= set(modules)   # the walk sees them
    unknown = {m: sorted(files)[:2] for m, files in modules.items() if m not in distributions}
    assert not unknown, f"imported but no installed distribution provides them: {unknown}"
    missing = {m: sorted(files)[:2] for m, files in modules.items()
               if not {_name(d) for d in distributions[m]} & runtime}
    assert not missing, f"imported but not in [project] dependencies: {missing}"


def test_hubdata_is_a_runtime_dependency_of_the_publish_path():
    """The round's validation reads hubdata's schema: a plain install must have it."""
    assert "hubdata" in declared()
    assert "pipeline/outputs/hubverse_validation.py" in imported_modules()["hubdata"]


def test_every_declared_dependency_is_imported_or_a_documented_pin():
    distributions = md.packages_distributions()
    used = {_name(d) for m in imported_modules() for d in distributions.get(m, [])}
    unused = declared() - used - set(PINS)
    assert not unused, f"declared in [project] dependencies but imported nowhere: {unused}"
    for pin, needed_by in PINS.items():   # a pin is of something a dependency really requires
        requires = {_name(r) for r in md.requires(needed_by) or [] if "extra ==" not in r}
        assert pin in requires and needed_by in declared(), (pin, needed_by)


def test_the_models_metadata_ship_inside_the_package():
    """A plain `pip install .` publishes a round: the metadata the publish path reads lie in
    the package, and pyproject's package data names them (a repo-level folder is not
    installed)."""
    import fnmatch
    import tomllib
    from pathlib import Path

    import pipeline
    from pipeline.outputs.hubverse_round import MODEL_METADATA_DIR

    package = Path(pipeline.__file__).resolve().parent
    files = sorted(MODEL_METADATA_DIR.glob("*.yml"))
    assert [f.name for f in files] == ["flowcast-nfens.yml", "flowcast-nfhub.yml"]
    shipped = tomllib.loads((package.parent / "pyproject.toml").read_text())[
        "tool"]["setuptools"]["package-data"]["pipeline"]
    assert all(any(fnmatch.fnmatch(str(f.relative_to(package)), g) for g in shipped)
               for f in files)


def test_the_shipped_metadata_meet_the_hubs_schema():
    """Each shipped model's metadata meets the hub's model-metadata schema (its 200-character
    ``methods`` included): a description edited past the limit fails here, not at a round."""
    import json
    from pathlib import Path

    from pipeline.outputs.hubverse_round import (MODEL_METADATA_DIR, load_model_metadata,
                                                 validate_model_metadata)

    schema = json.loads((Path(__file__).resolve().parents[1] / "hub-config"
                         / "model-metadata-schema.json").read_text())
    for path in sorted(MODEL_METADATA_DIR.glob("*.yml")):
        metadata = load_model_metadata(path)
        validate_model_metadata(metadata, path.stem, schema)
        assert 0 < len(metadata["methods"]) <= 200, path.name
