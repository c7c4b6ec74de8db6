"""A round of the CDC COVID-19 Forecast Hub: written from a long hubverse frame with its model
metadata, validated against the hub's own tasks.json (``../shared/data/nhsn/hub-config``, read
in place), read back with ``hubdata`` as a hub user would, and broken rounds refused by name
with the last good file left as it was."""
from __future__ import annotations

import datetime as dt
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

from pipeline.outputs.hubverse import HUB_QUANTILE_LEVELS
from pipeline.outputs.hubverse_round import (CDC_HUB_MODEL_ID, compound_sample_ids,
                                             load_model_metadata, write_hub_round)
from pipeline.outputs.hubverse_validation import (HubValidationError, load_tasks_config,
                                                  validate_model_output)

REPO = Path(__file__).resolve().parents[1]
NHSN = REPO.parent / "shared" / "data" / "nhsn"
ROUND = dt.date(2025, 10, 18)
TARGETS = ("wk inc covid hosp", "wk inc covid prop ed visits")


@pytest.fixture(scope="module")
def hub() -> dict:
    if not (NHSN / "hub-config" / "tasks.json").exists():
        pytest.fail(f"the hub's config expected at {NHSN / 'hub-config'} (../shared beside "
                    "the repo)")
    return {"tasks": load_tasks_config(NHSN / "hub-config" / "tasks.json"),
            "locations": pd.read_csv(NHSN / "locations.csv", dtype={"location": str}),
            "metadata": load_model_metadata(REPO / "pipeline" / "outputs" / "model_metadata" / f"{CDC_HUB_MODEL_ID}.yml"),
            "schema": json.loads((REPO / "hub-config" / "model-metadata-schema.json")
                                 .read_text())}


def _round(locations: list[str], n_samples: int = 200, seed: int = 0) -> pd.DataFrame:
    """Log-normal forecasts of every location × target × horizon −1..3: quantiles at the 23
    levels and ``n_samples`` sample paths numbered 1..n in every location (as a forecaster
    makes them), median 100·(1 + horizon/10) admissions or a 2 % ED share."""
    rng = np.random.default_rng(seed)
    tasks = pd.MultiIndex.from_product([locations, TARGETS, range(-1, 4)],
                                       names=["location", "target", "horizon"]) \
        .to_frame(index=False)
    median = np.where(tasks.target == TARGETS[0], 100.0, 0.02) * (1 + tasks.horizon / 10)
    z = norm.ppf(HUB_QUANTILE_LEVELS)
    q = tasks.loc[tasks.index.repeat(len(z))].assign(
        output_type="quantile", output_type_id=np.tile(HUB_QUANTILE_LEVELS, len(tasks)),
        value=(median.to_numpy()[:, None] * np.exp(0.3 * z)).ravel())
    paths = median.to_numpy()[:, None] * np.exp(0.3 * rng.standard_normal((len(tasks),
                                                                           n_samples)))
    s = tasks.loc[tasks.index.repeat(n_samples)].assign(
        output_type="sample", output_type_id=np.tile(np.arange(1, n_samples + 1), len(tasks)),
        value=paths.ravel())
    frame = pd.concat([q, s], ignore_index=True)
    frame["reference_date"] = pd.Timestamp(ROUND)
    frame["target_end_date"] = frame.reference_date + pd.to_timedelta(7 * frame.horizon, "D")
    return frame[["reference_date", "target", "horizon", "location", "target_end_date",
                  "output_type", "output_type_id", "value"]]


def _hub_dir(tmp_path: Path) -> Path:
    """A hub a user would clone: the CDC hub's config, and model-output to be filled."""
    root = tmp_path / "hub"
    shutil.copytree(NHSN / "hub-config", root / "hub-config")
    return root


def test_compound_sample_ids_are_unique_per_location_and_target():
    frame = compound_sample_ids(_round(["US", "06"], n_samples=3))
    samples = frame[frame.output_type == "sample"]
    ids = samples.groupby(["location", "target"]).output_type_id.agg(lambda s: sorted(set(s)))
    assert ids.map(len).tolist() == [3, 3, 3, 3]
    assert len(set().union(*ids)) == 12                     # no id shared by two compound tasks
    # one id is one trajectory across the five horizons
    assert samples.groupby("output_type_id").horizon.nunique().eq(5).all()
    quantiles = frame[frame.output_type == "quantile"]
    assert quantiles.output_type_id.tolist() == _round(["US", "06"], 3) \
        .query("output_type == 'quantile'").output_type_id.tolist()


def test_round_of_53_locations_is_written_valid_and_read_back_by_hubdata(tmp_path, hub):
    import hubdata  # a dev dependency: its absence is a failure, not a skip
    locations = hub["locations"].location.tolist()
    assert len(locations) == 53
    frame = compound_sample_ids(_round(locations))
    root = _hub_dir(tmp_path)
    written = write_hub_round(frame, hub_dir=root, model_id=CDC_HUB_MODEL_ID,
                              tasks=hub["tasks"], metadata=hub["metadata"],
                              metadata_schema=hub["schema"])
    assert written.path == root / "model-output" / "flowcast-nfhub" / \
        "2025-10-18-flowcast-nfhub.csv"
    assert written.metadata_path == root / "model-metadata" / "flowcast-nfhub.yml"
    assert load_model_metadata(written.metadata_path) == hub["metadata"]
    assert len(written.frame) == 53 * 2 * 5 * (23 + 200)
    text = written.path.read_text().splitlines()
    assert text[0] == ("reference_date,target,horizon,location,target_end_date,output_type,"
                       "output_type_id,value")
    assert text[1].startswith("2025-10-18,wk inc covid hosp,-1,01,2025-10-11,quantile,0.01,")

    table = hubdata.connect_hub(root).get_dataset().to_table()
    back = table.to_pandas()
    assert set(back.model_id) == {CDC_HUB_MODEL_ID} and len(back) == len(written.frame)
    assert str(table.schema.field("output_type_id").type) == "string"
    assert set(back.location) == set(locations)             # "01" .. "72" kept as text
    keys = ["target", "horizon", "location", "output_type", "output_type_id"]
    text_cells = pd.read_csv(written.path, dtype=str, keep_default_na=False)
    both = text_cells.assign(horizon=text_cells.horizon.astype(int),
                             value=text_cells.value.astype(float)) \
        .merge(back.assign(horizon=back.horizon.astype(int)), on=keys, how="outer",
               indicator=True, suffixes=("", "_hub"))
    assert (both._merge == "both").all()                     # the same rows, one to one
    np.testing.assert_array_equal(both.value_hub, both.value)
    assert (pd.to_datetime(both.target_end_date_hub) == pd.to_datetime(both.target_end_date)).all()
    # and the numbers are the frame's, to the file's 8 significant digits
    us = back[(back.location == "US") & (back.target == TARGETS[0]) & (back.horizon == 2)
              & (back.output_type == "quantile")]
    expected = 120.0 * np.exp(0.3 * norm.ppf(HUB_QUANTILE_LEVELS))
    np.testing.assert_allclose(us.sort_values("output_type_id", key=lambda c: c.astype(float))
                               .value, expected, rtol=1e-7)
    samples = back[back.output_type == "sample"].assign(horizon=lambda f: f.horizon.astype(int))
    assert samples.groupby(["location", "target"]).output_type_id.nunique().eq(200).all()
    assert samples.groupby("output_type_id").horizon.nunique().eq(5).all()  # one id, one path
    given = frame[frame.output_type == "sample"].set_index(keys).value
    np.testing.assert_allclose(samples.set_index(keys).value.loc[given.index], given, rtol=1e-7)


def _set(frame: pd.DataFrame, where: pd.Series, column: str, value) -> pd.DataFrame:  # noqa: ANN001
    out = frame.copy()
    if column == "value":
        out["value"] = out["value"].astype(float)
    else:
        out[column] = out[column].astype(object)
    out.loc[where, column] = value
    return out


def _q(frame: pd.DataFrame, level: float, loc: str = "06", horizon: int = 1) -> pd.Series:
    return (frame.output_type == "quantile") & (frame.output_type_id == level) & \
        (frame.location == loc) & (frame.horizon == horizon) & (frame.target == TARGETS[0])


BROKEN = [
    (lambda f: _set(f, _q(f, 0.5), "value", np.nan), r"value nan: hub values must be finite"),
    (lambda f: _set(f, _q(f, 0.5), "value", np.inf), r"value inf: hub values must be finite"),
    (lambda f: _set(f, _q(f, 0.01), "value", -1.0), r"value -1\.0: hub values must be finite"),
    (lambda f: f[~_q(f, 0.3)], r"lacks the levels \[0\.3\] \(incomplete quantile set: 22 of 23"),
    (lambda f: _set(f, _q(f, 0.6), "value", 1.0), r"decrease as the level rises"),
    (lambda f: _set(f, f.location == "06", "location", "78"), r"column 'location': '78' is not "
                                                               "one of"),
    (lambda f: _set(f, _q(f, 0.5), "target_end_date", pd.Timestamp("2025-11-01")),
     r"target_end_date 2025-11-01 is not reference_date 2025-10-18 \+ 7·horizon \(1\)"),
    (lambda f: _set(f, f.horizon == 3, "horizon", 4), r"column 'horizon': 4 is not one of"),
    (lambda f: _set(f, f.target == TARGETS[1], "target", "wk inc flu hosp"),
     r"column 'target': 'wk inc flu hosp' is not one of"),
    (lambda f: f[~((f.output_type == "sample") & (f.output_type_id == "7"))],
     r"199 samples for compound task \{'location': 'US', 'target': 'wk inc covid hosp'\}; the "
     r"hub asks for 200\.\.200"),
    (lambda f: f[~((f.output_type == "sample") & (f.output_type_id == "7") & (f.horizon == 2))],
     r"has 199 samples, its compound task has 200"),
    (lambda f: _set(f, (f.output_type == "sample") & (f.output_type_id == "0"),
                    "output_type_id", "1"), r"more than one|duplicated row"),
    (lambda f: _set(f, (f.output_type == "sample") & (f.location == "US")
                    & (f.target == TARGETS[1]), "output_type_id",
                    f[(f.output_type == "sample") & (f.location == "06")
                      & (f.target == TARGETS[0])].output_type_id.to_numpy()),
     r"sample id '\d+' is used in two compound tasks"),
    (lambda f: _set(f, (f.output_type == "sample") & (f.output_type_id == "5"),
                    "output_type_id", "sample-number-0005"), r"is too long"),
    (lambda f: pd.concat([f, f.iloc[:23].assign(reference_date=pd.Timestamp("2025-10-25"))]),
     r"a round file holds one reference_date"),
]


@pytest.mark.parametrize("mutate, match", BROKEN)
def test_broken_round_is_refused_and_the_last_good_file_kept(tmp_path, hub, mutate, match):
    good = compound_sample_ids(_round(["US", "06"]))
    root = _hub_dir(tmp_path)
    kwargs = dict(hub_dir=root, model_id=CDC_HUB_MODEL_ID, tasks=hub["tasks"],
                  metadata=hub["metadata"], metadata_schema=hub["schema"])
    first = write_hub_round(good, **kwargs)
    before = first.path.read_bytes()
    with pytest.raises(HubValidationError, match=match):
        write_hub_round(mutate(good), **kwargs)
    assert first.path.read_bytes() == before
    assert sorted(p.name for p in first.path.parent.iterdir()) == [first.path.name]


def test_metadata_must_be_the_models_and_meet_the_schema(tmp_path, hub):
    good = compound_sample_ids(_round(["US"]))
    kwargs = dict(hub_dir=_hub_dir(tmp_path), tasks=hub["tasks"], metadata_schema=hub["schema"])
    with pytest.raises(HubValidationError, match="model metadata is for 'flowcast-nfhub', the "
                                                 "round for 'flowcast-other'"):
        write_hub_round(good, model_id="flowcast-other", metadata=hub["metadata"], **kwargs)
    long = {**hub["metadata"], "methods": "x" * 201}
    with pytest.raises(HubValidationError, match="methods: '.*' is too long"):
        write_hub_round(good, model_id=CDC_HUB_MODEL_ID, metadata=long, **kwargs)
    assert not (kwargs["hub_dir"] / "model-output").exists()


@pytest.mark.parametrize("cell", ["nan", "inf", "-inf"])
def test_validator_refuses_a_file_holding_a_non_finite_value(tmp_path, hub, cell):
    written = write_hub_round(compound_sample_ids(_round(["US"])), hub_dir=_hub_dir(tmp_path),
                              model_id=CDC_HUB_MODEL_ID, tasks=hub["tasks"],
                              metadata=hub["metadata"])
    lines = written.path.read_text().splitlines()
    lines[4] = lines[4].rsplit(",", 1)[0] + "," + cell    # a JSON Schema number lets NaN pass
    written.path.write_text("\n".join(lines) + "\n")
    with pytest.raises(HubValidationError, match=rf"row 5: column 'value': {cell} is not a "
                                                 "finite number"):
        validate_model_output(written.path, hub["tasks"])


def test_a_hub_config_folder_without_tasks_json_is_refused_not_passed_over(tmp_path,
                                                                          monkeypatch):
    """The run's own check (the deployment passes no CLI): a folder given without a
    tasks.json is named, never replaced by the default hub's config; none given: the disease's
    hub beside the checkout, and RSV has none."""
    from pipeline.errors import ConfigError
    from pipeline.hub_round.run import DEFAULT_HUB_CONFIGS, HUB_CONFIG_ENV, HubRunConfig

    monkeypatch.delenv(HUB_CONFIG_ENV, raising=False)
    with pytest.raises(ConfigError, match=f"hub_config {tmp_path}: no readable tasks.json"):
        HubRunConfig(hub_config=str(tmp_path)).hub_config_dir()
    monkeypatch.setenv(HUB_CONFIG_ENV, str(tmp_path))
    with pytest.raises(ConfigError, match=f"\\${HUB_CONFIG_ENV} {tmp_path}"):
        HubRunConfig().hub_config_dir()
    monkeypatch.delenv(HUB_CONFIG_ENV)
    assert HubRunConfig().hub_config_dir() == DEFAULT_HUB_CONFIGS["covid"]
    assert HubRunConfig(disease="rsv").hub_config_dir() == DEFAULT_HUB_CONFIGS["rsv"]
