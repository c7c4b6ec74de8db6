"""`flowcast data …` on the real DataSF exports (offline; FLOWCAST_DATA_DIR in tmp via conftest)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from pipeline.cli.data import data_app
from pipeline.data.core.cache import DatasetCache
from pipeline.data.sf.datasf import CASES
from pipeline.io import atomic_write_json
from tests.test_datasf_client import EXPORTS, cache_snapshot
from tests.test_datasf_import import VACCINATIONS

cli = typer.Typer()
cli.add_typer(data_app, name="data")


def run(*args: str):  # type: ignore[no-untyped-def]
    return CliRunner().invoke(cli, ["data", *map(str, args)])


@pytest.fixture
def cache_root(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"


@pytest.fixture
def exports(datasf_dir: Path) -> dict[str, Path]:
    return {key: datasf_dir / rel for key, rel in EXPORTS.items()}


@pytest.mark.slow  # a fresh process imports the whole CLI (torch): ~5-9 s on a loaded machine
def test_flowcast_data_import_entry_point_on_the_real_cases_export(exports, tmp_path):
    """The 'Must show' run, through the installed console script in a fresh process."""
    data_dir = tmp_path / "elsewhere"
    env = {**os.environ, "FLOWCAST_DATA_DIR": str(data_dir)}
    flowcast = Path(sys.executable).with_name("flowcast")
    done = subprocess.run([str(flowcast), "data", "import", str(exports["cases"])], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert ("imported COVID-19_Cases_Over_Time.csv: cases (gyr2-k29z), 2020-03-03 … 2022-03-16, "
            "744 rows, final cumulative 122,918, data as of 2022-03-21T04:30:01") in done.stdout
    assert f"cache: {data_dir.resolve() / 'datasf'}" in done.stdout
    assert (data_dir / "datasf" / "gyr2-k29z" / "manifest.json").is_file()


def test_renamed_column_fails_naming_new_cases_and_leaves_cache_untouched(exports, tmp_path,
                                                                          cache_root):
    assert run("import", exports["cases"], exports["deaths"]).exit_code == 0
    before = cache_snapshot(cache_root)
    text = exports["cases"].read_text()
    bad = tmp_path / "COVID-19_Cases_Over_Time.csv"
    bad.write_text(text.replace("New Cases", "New Kases", 1))
    result = run("import", bad)
    assert result.exit_code == 1
    assert f"error: {bad}: missing column 'New Cases' (API field 'new_cases')" in result.output
    assert "'New Kases'" in result.output  # what the file has instead
    assert cache_snapshot(cache_root) == before


def test_if_empty_skips_a_cached_dataset(exports, cache_root):
    assert run("import", exports["cases"]).exit_code == 0
    before = cache_snapshot(cache_root)
    result = run("import", "--if-empty", exports["cases"], exports["tests"])
    assert result.exit_code == 0, result.output
    assert "skipped COVID-19_Cases_Over_Time.csv: cases (gyr2-k29z)" in result.output
    assert "cache already holds this dataset; left as is (--if-empty)" in result.output
    assert "imported Covid-19_Tests.csv: tests (nfpa-mg4g), 2020-03-01 … 2022-04-27, 788 rows" \
        in result.output
    assert {k: v for k, v in cache_snapshot(cache_root).items() if "gyr2-k29z" in k} == before


def test_unknown_export_names_the_file_and_expected_columns(datasf_dir, cache_root):
    path = datasf_dir / VACCINATIONS
    result = run("import", path)
    assert result.exit_code == 1
    assert f"error: {path}: cannot tell which DataSF dataset this is" in result.output
    assert "'DATE_ADMINISTERED'" in result.output
    assert ("cases (gyr2-k29z): 'Specimen Collection Date', 'New Cases', 'Cumulative Cases'"
            in result.output)
    assert cache_snapshot(cache_root) == {}


def test_status_shows_what_is_cached_and_its_age(exports, cache_root):
    empty = run("status")
    assert empty.exit_code == 0
    assert "cases (gyr2-k29z): not cached — `flowcast data fetch` or `flowcast data import FILE`" \
        in empty.output
    assert run("import", exports["cases"], exports["deaths"]).exit_code == 0
    # Age the cases copy by three days (the manifest's fetched_at is what status reads).
    cache = DatasetCache(cache_root)
    manifest = json.loads(cache.manifest_path(CASES).read_text())
    fetched = cache.read_manifest(CASES).fetched_at_dt - timedelta(days=3)
    atomic_write_json(cache.manifest_path(CASES), {**manifest, "fetched_at": fetched.isoformat()})
    out = run("status").output
    assert ("cases (gyr2-k29z): csv-import " in out and "744 rows 2020-03-03 … 2022-03-16; data "
            "as of 2022-03-21T04:30:01" in out and "(3.0 days ago)" in out)
    assert "deaths (g2di-xufg): csv-import" in out and "(0.0 days ago)" in out
    assert "tests (nfpa-mg4g): not cached" in out


def test_sir_offline_writes_csv_with_vintage(exports, tmp_path, cache_root):
    assert run("import", *exports.values()).exit_code == 0
    out = tmp_path / "sf_sir.csv"
    result = run("sir", "--out", out, "--offline")
    assert result.exit_code == 0, result.output
    frame = pd.read_csv(out)
    assert list(frame.columns) == ["date", "S", "I", "R"] and len(frame) == 730
    assert (frame["date"].iloc[0], frame["date"].iloc[-1]) == ("2020-03-03", "2022-03-02")
    assert (frame[["S", "I", "R"]].sum(axis=1) - 1.0).abs().max() < 1e-15
    provenance = json.loads(out.with_name("sf_sir.csv.provenance.json").read_text())
    assert provenance["vintage"]["data_as_of"] == "2022-03-21T04:30:01"
    assert provenance["vintage"]["trimmed_days"] == 14
    assert "data as of 2022-03-21T04:30:01" in result.output


def test_sir_offline_without_cache_names_flowcast_data_import(tmp_path):
    result = run("sir", "--out", tmp_path / "x.csv", "--offline")
    assert result.exit_code == 1
    assert "no cached DataSF cases data" in result.output
    assert "`flowcast data import FILE`" in result.output
    assert not (tmp_path / "x.csv").exists()


def test_plot_writes_figures_and_measured_overlap(exports, tmp_path, cache_root):
    assert run("import", *exports.values()).exit_code == 0
    out = tmp_path / "figs"
    result = run("plot", "--out", out, "--offline", "--n-trajectories", "60")
    assert result.exit_code == 0, result.output
    for name in ("sf_sir.png", "sf_sir_vs_prior.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads((out / "sf_prior_comparison.json").read_text())
    inside = report["comparison"]["states_aligned"]["inside"]
    assert set(inside) == {"S", "I", "R", "all"} and all(0 <= v <= 1 for v in inside.values())
    assert report["comparison"]["n_days"] == 730
    assert report["provenance"]["vintage"]["last_date_kept"] == "2022-03-02"
    assert "SF days inside the prior's 1–99 % state band (offset 0)" in result.output
