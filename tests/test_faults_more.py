"""Issue 22: the ten faults the outside probe still found. Every fault ends in the cache or one
named error. Served by the fake DataSF on 127.0.0.1 (``bench.faults``) through the real
``requests`` stack; each test asserts the message and that the cache bytes are unchanged.
(The fallback cases of the catalogue also run in tests/test_faults.py, parametrized.)
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from bench.faults import (FakeDataSF, api_rows, bytes_lost, cache_bytes, client_config,
                          closed_port_url, command_faults, fill_cache_from_api, header_drip,
                          held_cache_lock, live_request_threads, run_command_fault, with_value)
from pipeline.cli.output_paths import OutputPathError, output_dir, output_file
from pipeline.data.core.cache import DatasetCache
from pipeline.data.sf.datasf import CASES, DATASETS, DataSFClient, check_gate, UnreachableError
from pipeline.data.core.decoding import (PayloadRejectedError, decode_boundary, decode_csv_frame,
                                         decode_json_records)
from pipeline.data.sf.payloads import rows_frame
from pipeline.data.core.gate import CountBound, GateError, GateRules, Places, gate
from pipeline.data.core.plausibility import DAILY
from pipeline.data.sf.series import SFDataConfig, load_dataset, load_sf_series
from pipeline.data.sf.validation import validate_frame
from pipeline.errors import DataSourceError

REPO = Path(__file__).resolve().parents[1]
COMMANDS = {c.name: c for c in command_faults()}


@pytest.fixture(scope="module")
def rows() -> dict[str, list[dict[str, str]]]:
    return {key: api_rows(key) for key in DATASETS}


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"  # = $FLOWCAST_DATA_DIR (conftest)


def _serve_all(server: FakeDataSF, rows: dict[str, list[dict[str, str]]]) -> None:
    by_id = {DATASETS[k].dataset_id: r for k, r in rows.items()}
    server.respond(lambda h: h.send_rows(by_id[h.path.split("/")[2].split(".")[0]]))


# ------------------------------------------------------------------ 1. the decode boundary


def test_decoder_exceptions_become_one_named_rejection():
    with pytest.raises(PayloadRejectedError, match=r"^invalid JSON from src \(200000 bytes\): "
                                                   r"nested too deeply to decode \(RecursionError"):
        decode_json_records(b"[" * 200_000, source="src")
    with pytest.raises(PayloadRejectedError, match=r"ValueError: Exceeds the limit \(4300 digits\)"):
        decode_json_records(b"[" + b"7" * 5000 + b"]", source="src")
    with pytest.raises(PayloadRejectedError, match=r"^invalid JSON from src: 40 bytes, more than "
                                                   r"the 10 a payload may have; refused unread"):
        decode_json_records(b"[" + b" " * 38 + b"]", source="src", max_bytes=10)
    with pytest.raises(PayloadRejectedError, match=r"src: not a readable CSV"):
        decode_csv_frame(b'a,b\n"1,2\n' * 3, source="src")
    # Whatever a parser raises (here MemoryError) is named, never a traceback.
    with pytest.raises(PayloadRejectedError, match=r"^invalid rows from x: too large to decode "
                                                   r"in memory \(MemoryError\)"):
        with decode_boundary("rows", "x"):
            raise MemoryError
    # A payload with nested values where strings belong reaches validation as a named error.
    with pytest.raises(DataSourceError, match=r"non-numeric value"):
        validate_frame(rows_frame([{"specimen_collection_date": "2020-03-03T00:00:00.000",
                                    "new_cases": {"a": [1]}, "cumulative_cases": "1"}]),
                       CASES, source="x")


def test_malformed_json_falls_back_to_the_untouched_cache(rows, data_dir):
    with FakeDataSF() as server:
        server.serve_rows(rows["cases"])
        config = SFDataConfig(datasets=("cases",), data_dir=data_dir,
                              client=client_config(server))
        load_dataset(CASES, config)
        before = cache_bytes(data_dir)
        for body, expect in ((b"[" * 200_000, "nested too deeply to decode (RecursionError"),
                             (b'[{"new_cases": ' + b"9" * 5000 + b"}]",
                              "Exceeds the limit (4300 digits)")):
            server.respond(lambda h, body=body: h.send_body(200, body))
            _, provenance = load_dataset(CASES, config)
            assert provenance.from_cache
            assert provenance.notes[0].startswith(
                f"DataSF payload rejected, cache kept: invalid JSON from {server.url}/resource/"
                f"gyr2-k29z.json?")
            assert expect in provenance.notes[0]
    assert bytes_lost(before, cache_bytes(data_dir)) == 0


# ------------------------------------------------------------------ 2. plausibility


def test_the_real_series_are_plausible(rows):
    for key, spec in DATASETS.items():
        validated = validate_frame(rows_frame(rows[key]), spec, source=key)
        check_gate(validated.frame, spec, source=key)


def test_absurd_count_in_the_open_window_never_replaces_the_cache(rows, data_dir):
    poisoned = with_value(rows["cases"], "new_cases", "99999999", index=len(rows["cases"]) - 10)
    with FakeDataSF() as server:
        server.serve_rows(rows["cases"])
        config = SFDataConfig(datasets=("cases",), data_dir=data_dir,
                              client=client_config(server))
        load_dataset(CASES, config)
        before = cache_bytes(data_dir)
        server.serve_rows(poisoned)
        _, provenance = load_dataset(CASES, config)
        assert provenance.notes[0] == (
            f"DataSF payload rejected, cache kept: {server.url}/resource/gyr2-k29z.json: "
            f"implausible count 99,999,999 in 'new_cases' on 2022-03-07: more than 5% of the "
            f"population 873,965 (2020 Census) in one day; refused")
        assert bytes_lost(before, cache_bytes(data_dir)) == 0
        # --accept-revisions does not take it either: no review makes it true.
        _, accepted = load_dataset(CASES, replace(config, accept_revisions=True))
        assert accepted.from_cache and bytes_lost(before, cache_bytes(data_dir)) == 0


def test_a_poisoned_cache_is_repaired_by_the_next_correct_fetch_not_held(rows, data_dir):
    """A cache poisoned by an older flowcast is no reference for the revision policy."""
    poisoned = with_value(rows["cases"], "new_cases", "99999999", index=len(rows["cases"]) - 10)
    payload = json.dumps(poisoned).encode()
    cache = DatasetCache(data_dir)
    cache.store(CASES, payload, suffix="json", source_kind="api", source="old flowcast",
                row_count=744, first_date="2020-03-03", last_date="2022-03-16",
                data_as_of=None, final_cumulative=None)
    with FakeDataSF() as server:
        server.serve_rows(rows["cases"])
        _, provenance = load_dataset(CASES, SFDataConfig(datasets=("cases",), data_dir=data_dir,
                                                         client=client_config(server)))
    assert not provenance.from_cache
    assert not (cache.directory(CASES) / "held").exists()


def test_history_bound_names_the_day_and_the_bracket():
    frame = pd.DataFrame({"place": "X", "date": pd.date_range("2021-01-01", periods=40),
                          "n": [100] * 35 + [30_000] + [100] * 4})
    rules = GateRules(source="t", places=Places("place", {"X": 1_000_000}, "a table"),
                      counts=(CountBound("n", per_day=0.05, per_week=0.10),), jump=DAILY)
    with pytest.raises(GateError, match=r"^s: implausible count 30,000 in 'n' on "
                                        r"2021-02-05: more than 20× the plausible "
                                        r"bracket of the previous 28 day\(s\) "
                                        r"\(median 100, largest of the last 7 100, "
                                        r"bound 3,000\); refused"):
        gate(frame, rules, source="s")


# ------------------------------------------------------------------ 3. no configuration at import


def test_a_base_url_without_scheme_breaks_no_import_and_no_offline_command(data_dir):
    env = {**os.environ, "FLOWCAST_DATASF_BASE_URL": "data.sfgov.org",
           "PYTHONPATH": str(REPO)}
    probe = subprocess.run(
        [sys.executable, "-c", "import pipeline.data.sf.series, pipeline.data.sf.sir_transform, "
                               "pipeline.data.sf.csv_import, pipeline.cli.data; print('imported')"],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert probe.returncode == 0 and probe.stdout.strip() == "imported", probe.stderr
    result = run_command_fault(COMMANDS["base-url-without-scheme"], data_dir.parent)
    assert result.passed, result


# ------------------------------------------------------------------ 4. output paths


@pytest.mark.parametrize("name", [n for n in COMMANDS if n.startswith(("smc", "data", "sim"))])
def test_every_out_option_is_checked_in_one_place(name, tmp_path):
    result = run_command_fault(COMMANDS[name], tmp_path)
    assert result.passed, result
    assert result.bytes_lost == 0


def test_output_path_rule(tmp_path):
    (tmp_path / "old.csv").write_text("old")
    assert output_file(tmp_path / "old.csv") == tmp_path / "old.csv"  # replaced when written
    assert output_file(tmp_path / "new" / "deep" / "f.csv")  # parents created when written
    with pytest.raises(OutputPathError, match=rf"--out {tmp_path}/old.csv/f.csv: {tmp_path}/"
                                              r"old.csv is a file, so .* cannot be created"):
        output_file(tmp_path / "old.csv" / "f.csv")
    with pytest.raises(OutputPathError, match=r"is a file; --out names a directory"):
        output_dir(tmp_path / "old.csv")
    assert output_dir(tmp_path / "figs") == tmp_path / "figs"
    assert not (tmp_path / "figs").exists()  # created by the writer, not by the check


def test_data_sir_overwrites_an_existing_file_atomically(rows, data_dir, tmp_path):
    fill_cache_from_api(data_dir)
    out = tmp_path / "sir.csv"
    out.write_text("stale")
    from pipeline.cli.data import data_app
    result = CliRunner().invoke(data_app, ["sir", "--offline", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert out.read_text().startswith("date,S,I,R")
    provenance = json.loads((tmp_path / "sir.csv.provenance.json").read_text())
    assert {d["final_url"] for d in provenance["datasets"]} >= {
        d["source"] for d in provenance["datasets"]}


# ------------------------------------------------------------------ 5. no thread left behind


def test_no_request_thread_outlives_its_fetch(rows):
    """A server that drips its headers: the fetch gives up at its deadline and shuts the
    sockets, so neither the client's threads nor the server's handlers (whose writes fail once
    the socket is shut) are still running a moment later."""
    with FakeDataSF() as server:
        server.respond(header_drip)
        before = {t.ident for t in threading.enumerate()}
        client = DataSFClient(client_config(server, request_deadline_s=0.5,
                                            fetch_deadline_s=1.2, max_retries=3))
        started = time.monotonic()
        with pytest.raises(DataSourceError, match=r"deadline"):
            client.fetch(CASES)
        assert time.monotonic() - started < 3.0
        assert live_request_threads() == []
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline and \
                [t for t in threading.enumerate() if t.ident not in before]:
            time.sleep(0.05)
        assert [t.name for t in threading.enumerate() if t.ident not in before] == []
        assert len(server.seen) >= 2  # the retries ran, and each of their threads ended too


# ------------------------------------------------------------------ 6. a stuck lock


def test_stuck_cache_lock_falls_back_and_goes_on_with_the_other_datasets(rows, data_dir):
    with FakeDataSF() as server:
        _serve_all(server, rows)
        client = client_config(server)
        load_sf_series(SFDataConfig(data_dir=data_dir, client=client))
        before = cache_bytes(data_dir)
        with held_cache_lock(data_dir, CASES.dataset_id):
            started = time.monotonic()
            series = load_sf_series(SFDataConfig(data_dir=data_dir, client=client,
                                                 lock_timeout_s=0.3))
            assert time.monotonic() - started < 3.0
    cases, deaths, tests = series.provenance.datasets
    assert cases.from_cache and cases.notes[0].startswith(
        f"DataSF payload fetched but not stored, cache kept: data cache "
        f"{data_dir / 'datasf' / 'gyr2-k29z'}: still locked after 0 s by pid {os.getpid()}")
    assert not deaths.from_cache and not tests.from_cache
    assert len(series.frame) == 730
    cases_files = {k: v for k, v in before.items() if CASES.dataset_id in k}
    assert cases_files and bytes_lost(cases_files, cache_bytes(data_dir)) == 0


# ------------------------------------------------------------------ also


def test_unreachable_is_learned_in_seconds_and_short_circuits_the_run(rows, data_dir):
    with FakeDataSF() as server:
        _serve_all(server, rows)
        load_sf_series(SFDataConfig(data_dir=data_dir, client=client_config(server)))
    before = cache_bytes(data_dir)
    # The default retry schedule (4 retries, 1 s doubling) would cost 15 s per dataset.
    client = client_config(server, max_retries=4, backoff_base_s=1.0)
    config = SFDataConfig(data_dir=data_dir, client=replace(client, base_url=closed_port_url()))
    started = time.monotonic()
    series = load_sf_series(config)
    assert time.monotonic() - started < 2.0
    first, *others = series.provenance.datasets
    assert first.from_cache and "cannot connect to 127.0.0.1:" in first.notes[0]
    assert "Connection refused" in first.notes[0] and "not retried" in first.notes[0]
    assert all(p.from_cache and f"was not retried for {p.dataset_key}" in p.notes[0]
               for p in others)
    assert bytes_lost(before, cache_bytes(data_dir)) == 0
    with pytest.raises(UnreachableError):
        DataSFClient(config.client).fetch(CASES)


def test_server_ignoring_offset_stops_at_the_first_repeated_page_and_memory_is_bounded(rows):
    with FakeDataSF() as server:
        server.respond(lambda h: h.send_body(200, json.dumps(rows["cases"][:100]).encode()))
        with pytest.raises(DataSourceError, match=r"the page at \$offset=100 repeats the page at "
                                                  r"\$offset=0 \(the server ignores \$offset\?\)"):
            DataSFClient(client_config(server, page_size=100)).fetch(CASES)
        assert len(server.seen) == 2
        # Distinct pages that never end: stopped by the bytes of all pages together.
        pages = iter(range(10**6))
        server.respond(lambda h: h.send_body(200, json.dumps(
            [{"n": f"{next(pages)}", "pad": "x" * 100}] * 100).encode()))
        with pytest.raises(DataSourceError, match=r"hold [\d,]+ bytes, more than the 50,000 one "
                                                  r"dataset may have; stopping"):
            DataSFClient(client_config(server, page_size=100, max_fetch_bytes=50_000)).fetch(
                CASES)
        assert len(server.seen) <= 2 + 5
