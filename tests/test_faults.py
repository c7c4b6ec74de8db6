"""Issue 15: a good cache is never lost. Every failure of the fault-injection probe, served by a
fake DataSF on 127.0.0.1 (``bench.faults.FakeDataSF``) through the real ``requests`` stack; each
test asserts the message and that the cache files are byte-identical afterwards.
"""
from __future__ import annotations

import gzip
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest
import requests
import torch
from typer.testing import CliRunner

from bench.faults import (TOKEN, FakeDataSF, api_rows, bytes_lost, cache_bytes, client_config,
                          faults, redirect, run_fault, with_value)
from pipeline.data.core.cache import CacheDamagedError, DatasetCache
from pipeline.data.sf.csv_import import import_csv_exports
from pipeline.data.sf.datasf import (BASE_URL_ENV, CASES, DEATHS, TESTS, ClientConfig, DataSFClient,
                                     parse_retry_after)
from pipeline.data.sf.series import SFDataConfig, load_dataset, load_sf_series
from pipeline.errors import CheckpointError, ValidationError
from pipeline.io import LockTimeoutError
from pipeline.training.model_store import ModelStore
from pipeline.outputs.run_folders import RunOutputs

CASES_EXPORT = "AndrewCorry__data_wrangling_1/COVID-19_Cases_Over_Time.csv"
FAULTS = {f.name: f for f in faults()}
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rows() -> dict[str, list[dict[str, str]]]:
    return {key: api_rows(key) for key in ("cases", "deaths", "tests")}


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"  # = $FLOWCAST_DATA_DIR (conftest)


def _config(server: FakeDataSF, data_dir: Path, **client: float) -> SFDataConfig:
    return SFDataConfig(datasets=("cases",), data_dir=data_dir,
                        client=client_config(server, **client))


# ------------------------------------------------------------------ every fault, cache kept


@pytest.mark.parametrize("name", list(FAULTS))
def test_fault_falls_back_to_the_untouched_cache(name, rows, data_dir):
    """Cases 1-5 of the issue: poisoned counts, shrinkage, transport errors, no deadline,
    Retry-After, cross-host redirect (plus the faults that already held: 429, 500, ...)."""
    result = run_fault(FAULTS[name], rows["cases"], data_dir)
    assert FAULTS[name].expect in result.note, result.note
    assert "using cache, fetched 0 days ago" in result.note
    assert result.bytes_lost == 0
    assert result.passed, result
    assert result.seconds < 4.0  # trickle included: bounded by the deadlines, not the server


def test_rejected_payload_without_cache_writes_nothing(rows, data_dir):
    with FakeDataSF() as server:
        server.serve_rows(with_value(rows["cases"], "new_cases", "inf"))
        with pytest.raises(ValidationError, match=r"non-finite count 'inf' in 'New Cases' at row "
                                                  r"101 \(date 2020-06-11\)"):
            load_dataset(CASES, _config(server, data_dir))
    assert cache_bytes(data_dir) == {}


def test_revision_beyond_policy_is_held_for_review_and_accepted_on_request(rows, data_dir):
    revised = FAULTS["revised-settled-days"].responder(rows["cases"],
                                                      None)  # type: ignore[arg-type]
    with FakeDataSF() as server:
        server.serve_rows(rows["cases"])
        load_dataset(CASES, _config(server, data_dir))
        before = cache_bytes(data_dir)
        server.respond(revised)
        _, provenance = load_dataset(CASES, _config(server, data_dir))
        held = [p for p in (DatasetCache(data_dir).directory(CASES) / "held").iterdir()
                if not p.name.endswith(".reason.json")]
        assert len(held) == 1 and f"payload held in {held[0]}" in provenance.notes[0]
        assert "e.g. 2020-12-28 398 -> 1,194; held for review" in provenance.notes[0]
        assert bytes_lost(before, cache_bytes(data_dir)) == 0
        # After review, --accept-revisions takes it.
        _, accepted = load_dataset(CASES, replace(_config(server, data_dir),
                                                  accept_revisions=True))
        assert not accepted.from_cache and accepted.sha256[:16] == held[0].stem[len("payload-"):]


def test_small_trailing_revisions_are_accepted(rows, data_dir):
    """DataSF's normal backfill (the last days change) is not held."""
    revised = [dict(r) for r in rows["cases"]]
    for row in revised[-10:]:
        row["new_cases"] = str(int(row["new_cases"]) + 40)
    with FakeDataSF() as server:
        server.serve_rows(rows["cases"])
        load_dataset(CASES, _config(server, data_dir))
        server.serve_rows(revised)
        _, provenance = load_dataset(CASES, _config(server, data_dir))
    assert not provenance.from_cache


# ------------------------------------------------------------------ transport details


def test_gzip_bodies_are_decoded(rows, data_dir):
    body = gzip.compress(json.dumps(rows["cases"]).encode())
    with FakeDataSF() as server:
        server.respond(lambda h: h.send_body(200, body, headers={"Content-Encoding": "gzip"}))
        validated, provenance = load_dataset(CASES, _config(server, data_dir))
    assert len(validated.frame) == 744 and not provenance.from_cache


def test_retry_after_is_honoured(rows):
    answers = iter([lambda h: h.send_body(429, b"slow down", headers={"Retry-After": "7"}),
                    lambda h: h.send_rows(rows["cases"])])
    slept: list[float] = []
    with FakeDataSF() as server:
        server.respond(lambda h: next(answers)(h))
        client = DataSFClient(client_config(server, backoff_base_s=0.5), sleep=slept.append)
        result = client.fetch(CASES)
    assert slept == [7.0] and len(result.rows) == 744  # not the 0.5 s backoff
    assert parse_retry_after("Wed, 21 Oct 2015 07:28:00 GMT",
                             now=pd.Timestamp("2015-10-21T07:27:30Z").to_pydatetime()) == 30.0


def test_same_host_redirect_keeps_token_and_records_final_url(rows, data_dir):
    def respond(h):
        if h.path.startswith("/resource/"):
            redirect(f"/mirror{h.path}")(h)
        else:
            h.send_rows(rows["cases"])

    session = requests.Session()
    with FakeDataSF() as server:
        server.respond(respond)
        _, provenance = load_dataset(CASES, _config(server, data_dir), session=session)
        assert [s.path.split("?")[0] for s in server.seen] == [
            "/resource/gyr2-k29z.json", "/mirror/resource/gyr2-k29z.json"]
        assert all(s.headers.get("X-App-Token") == TOKEN for s in server.seen)
        manifest = DatasetCache(data_dir).read_manifest(CASES)
        assert manifest.source == f"{server.url}/resource/gyr2-k29z.json"
        assert manifest.final_url == f"{server.url}/mirror/resource/gyr2-k29z.json"
    assert "X-App-Token" not in session.headers  # never a session default


def test_cross_host_redirect_never_receives_the_token(rows, data_dir):
    with FakeDataSF() as server, FakeDataSF() as other:
        other.serve_rows(rows["cases"])
        server.respond(redirect(f"{other.url}/resource/gyr2-k29z.json"))
        with pytest.raises(ValidationError.__mro__[1], match=r"redirects \(HTTP 302\) to "
                           rf"{other.url}/resource/gyr2-k29z.json: refused"):
            load_dataset(CASES, _config(server, data_dir))
        assert other.seen == []
    assert cache_bytes(data_dir) == {}


def test_base_url_and_token_from_environment_and_cli(rows, data_dir, monkeypatch):
    by_id = {CASES.dataset_id: rows["cases"], DEATHS.dataset_id: rows["deaths"],
             TESTS.dataset_id: rows["tests"]}
    from pipeline.cli.data import data_app as app

    with FakeDataSF() as server:
        server.respond(lambda h: h.send_rows(by_id[h.path.split("/")[2].split(".")[0]]))
        monkeypatch.setenv(BASE_URL_ENV, server.url)
        monkeypatch.setenv("FLOWCAST_DATASF_APP_TOKEN", "from-env")
        assert ClientConfig().base_url == server.url and ClientConfig().token() == "from-env"
        assert "from-env" not in repr(ClientConfig(app_token="from-env"))
        monkeypatch.delenv(BASE_URL_ENV)
        result = CliRunner().invoke(app, ["fetch", "--base-url", server.url,
                                          "--app-token", "from-cli"])
        assert result.exit_code == 0, result.output
        assert {s.headers.get("X-App-Token") for s in server.seen} == {"from-cli"}
    assert "cases (gyr2-k29z) from DataSF: 744 rows" in result.output
    manifest = DatasetCache(data_dir).read_manifest(TESTS)
    assert manifest.source == f"{server.url}/resource/nfpa-mg4g.json"
    bad = CliRunner().invoke(app, ["fetch", "--base-url", "ftp://mirror"])
    assert bad.exit_code == 1
    assert bad.output.strip().splitlines()[-1] == (
        "error: DataSF base URL must be http(s)://host[/path], got 'ftp://mirror' (--base-url / "
        "$FLOWCAST_DATASF_BASE_URL)")


# ------------------------------------------------------------------ the smaller items


def test_bad_manifest_date_is_one_named_error(datasf_dir, data_dir):
    from pipeline.cli.data import data_app as app

    import_csv_exports([datasf_dir / CASES_EXPORT])
    path = DatasetCache(data_dir).manifest_path(CASES)
    manifest = json.loads(path.read_text())
    path.write_text(json.dumps({**manifest, "fetched_at": "last Tuesday"}))
    message = (f"damaged cache manifest {path}: fetched_at 'last Tuesday' is not an ISO-8601 "
               f"timestamp; re-run `flowcast data fetch` or `flowcast data import FILE`")
    with pytest.raises(CacheDamagedError) as info:
        load_sf_series(SFDataConfig(datasets=("cases",), trailing_days=0), offline=True)
    assert str(info.value) == message
    result = CliRunner().invoke(app, ["status"])
    assert result.exit_code == 0 and f"cases (gyr2-k29z): {message}" in result.output
    path.write_text(json.dumps({**manifest, "last_date": "2022-13-45"}))
    with pytest.raises(CacheDamagedError, match="last_date '2022-13-45' is not a YYYY-MM-DD"):
        DatasetCache(data_dir).read_manifest(CASES)


def test_if_empty_repairs_a_damaged_dataset(datasf_dir, data_dir):
    export = datasf_dir / CASES_EXPORT
    import_csv_exports([export])
    cache = DatasetCache(data_dir)
    good = cache.read_manifest(CASES)
    payload = cache.directory(CASES) / good.payload_file
    good_bytes = payload.read_bytes()
    payload.write_bytes(payload.read_bytes()[:-200])  # bit rot
    [summary] = import_csv_exports([export], if_empty=True)
    assert summary.imported and summary.note.startswith(
        f"repaired a damaged cache: cached payload {payload} does not match its manifest sha256")
    repaired = cache.load(CASES)
    assert repaired.payload == good_bytes and repaired.manifest.sha256 == good.sha256
    # Intact: left as is.
    [again] = import_csv_exports([export], if_empty=True)
    assert not again.imported and "left as is (--if-empty)" in again.note


def test_stale_staging_and_building_folders_are_swept(tmp_path):
    day_ago = time.time() - 86_400 - 60
    outputs = RunOutputs(tmp_path / "reports")
    old = outputs.root / ".staging-2022-03-07-20220307T000000Z-dead"
    recent = outputs.root / ".staging-2022-03-07-20220308T000000Z-live"
    for folder in (old, recent):
        (folder / "tables").mkdir(parents=True)
    os.utime(old, (day_ago, day_ago))
    staging = outputs.begin("2022-03-14", "new")
    assert not old.exists() and recent.exists() and staging.exists()

    store = ModelStore(tmp_path / "models")
    dead = store.root / ".abc123.xyz.building"
    (dead / "forward").mkdir(parents=True)
    os.utime(dead, (day_ago, day_ago))
    store.put("k" * 64, lambda out: (out / "w.pt").write_bytes(b"w") and None)
    assert not dead.exists()


def test_two_runs_cannot_interleave_their_outputs(tmp_path):
    first, second = RunOutputs(tmp_path), RunOutputs(tmp_path, lock_timeout_s=0.2)
    with first.staged("2022-03-07", "one"):
        with pytest.raises(LockTimeoutError, match=rf"output directory {tmp_path} \(another "
                                                   r"weekly run is writing its report there\): "
                                                   r"still locked after 0 s by pid \d+"):
            second.begin("2022-03-07", "two")
    assert second.begin("2022-03-07", "two").exists()  # free again


def test_swapped_forward_and_backward_checkpoints_are_refused(tmp_path, monkeypatch):
    """Both directions share one architecture, so only the recorded direction tells them apart.
    The checkpoints are stand-ins (load_checkpoint stubbed): the check is in the loader."""
    from types import SimpleNamespace
    from unittest.mock import MagicMock

    import pipeline.forecast.joint_models
    from pipeline.forecast import resolve_config
    from pipeline.forecast.joint_models import load_models as _load_models
    from pipeline.models.estimator import ConditionalEstimator

    recorded = {"forward": "backward", "backward": "forward"}  # the two files swapped on disk

    def fake_load(path, expected_config=None):
        meta = SimpleNamespace(extra={"direction": recorded[Path(path).parent.name]}, history=[])
        return SimpleNamespace(estimator=MagicMock(spec=ConditionalEstimator), meta=meta)

    monkeypatch.setattr(pipeline.forecast.joint_models, "load_checkpoint", fake_load)
    entry = SimpleNamespace(path=tmp_path / "entry", key="k", reused=True)
    with pytest.raises(CheckpointError) as info:
        _load_models(resolve_config("tiny"), entry)
    assert str(info.value) == (
        f"{entry.path / 'forward' / 'model.pt'} is a backward model (checkpoint metadata "
        f"direction) in the forward slot: forward and backward checkpoints swapped; retrain "
        f"(--retrain)")
    recorded["forward"], recorded["backward"] = "forward", "backward"
    assert _load_models(resolve_config("tiny"), entry).key == "k"  # in place: loads


def test_killed_run_does_not_orphan_the_temporary_prefect_server(tmp_path):
    """kill -9 of a process that started Prefect's ephemeral server: the guard stops it."""
    psutil = pytest.importorskip("psutil")
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(PREFECT_HOME=str(tmp_path / "prefect"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_LOGGING_LEVEL="ERROR")
    script = ("import time; from flows.server_guard import ephemeral_api\n"
              "with ephemeral_api() as pid:\n    print(pid, flush=True); time.sleep(120)")
    run = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        server_pid = int(run.stdout.readline())  # blocks until the server answers /health
        assert psutil.pid_exists(server_pid)
        run.send_signal(signal.SIGKILL)
        run.wait(10)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and psutil.pid_exists(server_pid) and \
                psutil.Process(server_pid).status() != psutil.STATUS_ZOMBIE:
            time.sleep(0.2)
        assert not psutil.pid_exists(server_pid) or \
            psutil.Process(server_pid).status() == psutil.STATUS_ZOMBIE
    finally:
        if run.poll() is None:
            run.kill()
