"""hubverse submission: a model-output file written from a published weekly forecast (here, one
made of simulated SIR paths) is valid under hub-config/tasks.json (checked with jsonschema plus
the set rules), its numbers are the forecast's own, and broken files are refused with an error
naming the rule."""
from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from pipeline.outputs.hubverse import (HUB_QUANTILE_LEVELS, SubmissionConfig, model_output_path,
                                       reference_date_for, hub_tasks_config, write_model_output)
from pipeline.outputs.hubverse_validation import (HubFormatError, HubValidationError,
                                                  load_tasks_config, validate_model_output)
from pipeline.backtest.result import QuantileForecast
from pipeline.systems.sir import simulate_sir

REPO = Path(__file__).resolve().parents[1]
TASKS = load_tasks_config(REPO / "hub-config" / "tasks.json")
N = 873_965
ORIGIN = pd.Timestamp("2022-03-12")   # a Saturday: the forecast's last day of data
RUN = dt.date(2022, 3, 16)            # epiweek 2022-03-13 .. 2022-03-19
REF = dt.date(2022, 3, 19)
LEVELS = np.asarray(HUB_QUANTILE_LEVELS)


def _forecast(n: int = 200, horizons: tuple[int, ...] = (1, 2, 3, 4)) -> QuantileForecast:
    """Weekly S/I/R paths of RK4 SIR runs with spread β, at ORIGIN + 7h; quantiles from them."""
    x0 = torch.tensor([[0.95, 2e-3, 0.048]], dtype=torch.float64).expand(n, 3).clone()
    beta = torch.linspace(0.05, 0.25, n, dtype=torch.float64)
    gamma = torch.full((n,), 0.1, dtype=torch.float64)
    daily = simulate_sir(x0, beta, gamma, 7 * max(horizons), 1.0).numpy()
    paths = daily[:, [7 * h for h in horizons]]
    infectious = np.quantile(paths[..., 1], LEVELS, axis=0).T            # (H, Q)
    return QuantileForecast("published", ORIGIN, horizons, LEVELS,
                            {"I": infectious, "cases": infectious * N}, paths=paths)


def _write(tmp_path: Path, run: dt.date = RUN, forecast: QuantileForecast | None = None):
    forecast = forecast if forecast is not None else _forecast()
    return forecast, write_model_output(forecast, population=N, run_date=run, hub_dir=tmp_path,
                                        tasks=TASKS)


def test_reference_date_is_the_saturday_ending_the_epiweek():
    assert reference_date_for(RUN) == REF
    assert reference_date_for(dt.date(2022, 3, 13)) == REF      # Sunday starts the epiweek
    assert reference_date_for(dt.date(2022, 3, 19)) == REF      # Saturday ends it
    assert reference_date_for(dt.date(2022, 3, 20)) == dt.date(2022, 3, 26)


def test_written_file_is_valid_and_carries_the_forecasts_numbers(tmp_path):
    forecast, sub = _write(tmp_path)
    assert sub.path == (tmp_path / "model-output" / "flowcast-nfens"
                        / "2022-03-19-flowcast-nfens.csv")
    # the week ending 03-12 (horizon -1) is the origin's own, observed week
    assert sub.reference_date == REF and sub.horizons == (0, 1, 2, 3)
    assert set(sub.omitted) == {-1} and "is observed" in sub.omitted[-1]
    frame = validate_model_output(sub.path, TASKS)
    assert list(frame.columns) == ["reference_date", "target", "horizon", "location",
                                   "target_end_date", "output_type", "output_type_id", "value"]
    assert set(frame["target"]) == {"wk inc case", "I prop"} and set(frame["location"]) == {"06075"}
    assert len(frame) == 4 * 2 * (23 + 200)        # 4 horizons x 2 targets x (23 q + 200 samples)
    samples = frame[frame["output_type"] == "sample"]
    assert sorted(set(samples["output_type_id"]), key=int)[:2] == ["1", "2"]
    assert samples["output_type_id"].nunique() == 200
    # hub horizon 0 is the forecast's first week (ending 03-19): its quantiles, unchanged
    h0 = frame[(frame["target"] == "wk inc case") & (frame["horizon"] == 0)]
    assert set(h0["target_end_date"]) == {"2022-03-19"}
    q = h0[h0["output_type"] == "quantile"].sort_values("output_type_id")
    np.testing.assert_allclose(q["value"], forecast.values["cases"][0], rtol=1e-7)
    first = h0[(h0["output_type"] == "sample") & (h0["output_type_id"] == "1")]
    assert first["value"].item() == pytest.approx(N * forecast.paths[0, 0, 1], rel=1e-7)
    i3 = frame[(frame["target"] == "I prop") & (frame["horizon"] == 3)
               & (frame["output_type"] == "quantile")].sort_values("output_type_id")
    np.testing.assert_allclose(i3["value"], forecast.values["I"][3], rtol=1e-7)
    assert (frame["value"] >= 0).all()
    quantiles = frame[frame["output_type"] == "quantile"].sort_values("output_type_id")
    assert (quantiles.groupby(["target", "horizon"])["value"].diff().dropna() >= 0).all()


def test_weeks_outside_the_forecast_are_left_out_with_a_reason(tmp_path, caplog):
    caplog.set_level("INFO")
    _, sub = _write(tmp_path, forecast=_forecast(horizons=(1, 2)))
    assert sub.horizons == (0, 1)
    assert set(sub.omitted) == {-1, 2, 3}
    assert "not one of the forecast's weeks" in sub.omitted[3]
    assert "horizon 3 left out" in caplog.text
    validate_model_output(sub.path, TASKS)


def test_bad_forecasts_are_refused(tmp_path):
    good = _forecast()
    kwargs = dict(population=N, run_date=RUN, hub_dir=tmp_path)
    paths = good.paths.copy()
    paths[2, 1, 1] = np.nan
    nan_paths = QuantileForecast("published", ORIGIN, good.horizons, LEVELS, good.values, paths)
    with pytest.raises(HubFormatError, match="NaN, inf or negative"):
        write_model_output(nan_paths, **kwargs)
    few = QuantileForecast("published", ORIGIN, good.horizons, LEVELS, good.values,
                           good.paths[:50])
    with pytest.raises(HubFormatError, match="200 sample paths required, got 50"):
        write_model_output(few, **kwargs)
    with pytest.raises(HubFormatError, match="no horizon .* covered"):
        write_model_output(good, population=N, run_date=dt.date(2022, 6, 1), hub_dir=tmp_path)
    assert not (tmp_path / "model-output").exists()


def _mutated(tmp_path: Path, mutate) -> Path:  # noqa: ANN001
    _, sub = _write(tmp_path)
    frame = pd.read_csv(sub.path, dtype=str, keep_default_na=False)
    mutated = mutate(frame)
    mutated.to_csv(sub.path, index=False)
    return sub.path


def _set(frame: pd.DataFrame, row: int, column: str, value: str) -> pd.DataFrame:
    frame.loc[row, column] = value
    return frame


@pytest.mark.parametrize("mutate, match", [
    (lambda f: _set(f, 3, "value", "-5"), r"row 5: column 'value': -5\.0 is less than the minimum"),
    (lambda f: _set(f, 3, "value", "abc"), r"row 5: column 'value' must be a number"),
    (lambda f: _set(f, 0, "target", "wk inc death"), r"column 'target': 'wk inc death' is not one"),
    (lambda f: _set(f, 0, "horizon", "4"), r"column 'horizon': 4 is not one"),
    (lambda f: _set(f, 0, "location", "06117"), r"column 'location': '06117' is not one"),
    (lambda f: _set(f, 0, "output_type_id", "0.33"), r"column 'output_type_id': 0.33 is not one"),
    (lambda f: _set(f, 0, "output_type", "mean"), r"output_type 'mean' is not one"),
    (lambda f: _set(f, 0, "target_end_date", "2022-03-26"),
     r"row 2: target_end_date 2022-03-26 is not reference_date 2022-03-19 \+ 7·horizon"),
    (lambda f: f.drop(index=5), r"lacks the levels \[0\.2\] \(incomplete quantile set"),
    (lambda f: _set(f, 1, "value", "0"), r"decrease as the level rises \(crossing quantiles\)"),
    (lambda f: f.drop(columns="location"), r"missing \['location'\]"),
    (lambda f: f.assign(model="x"), r"unexpected \['model'\]"),
    (lambda f: pd.concat([f, f.iloc[[0]]]), r"duplicated row"),
    (lambda f: f[~((f["output_type"] == "sample") & (f["output_type_id"].astype(float) > 50))],
     r"50 samples for compound task .*asks for 100\.\.200"),
    (lambda f: f.drop(index=f.index[(f["output_type"] == "sample")][0]),
     r"has 199 samples, its compound task has 200"),
])
def test_broken_file_is_refused_by_name(tmp_path, mutate, match):
    path = _mutated(tmp_path, mutate)
    with pytest.raises(HubValidationError, match=match):
        validate_model_output(path, TASKS)


def test_file_name_must_match_round_and_model(tmp_path):
    _, sub = _write(tmp_path)
    wrong = sub.path.with_name("2022-03-26-flowcast-nfens.csv")
    sub.path.rename(wrong)
    with pytest.raises(HubValidationError, match="differ from the file name's 2022-03-26"):
        validate_model_output(wrong, TASKS)
    other = tmp_path / "model-output" / "other-model" / "2022-03-19-flowcast-nfens.csv"
    other.parent.mkdir()
    wrong.rename(other)
    with pytest.raises(HubValidationError, match="differs from its folder 'other-model'"):
        validate_model_output(other, TASKS)


def test_hub_config_and_model_metadata():
    import jsonschema

    assert TASKS == hub_tasks_config(dt.date(2020, 3, 1), dt.date(2027, 12, 31))
    task = TASKS["rounds"][0]["model_tasks"][0]
    assert task["task_ids"]["horizon"]["optional"] == [-1, 0, 1, 2, 3]
    levels = task["output_type"]["quantile"]["output_type_id"]["required"]
    assert levels == list(HUB_QUANTILE_LEVELS)
    refs = [dt.date.fromisoformat(d) for d in task["task_ids"]["reference_date"]["optional"]]
    assert all(d.weekday() == 5 for d in refs)  # Saturdays
    admin = json.loads((REPO / "hub-config" / "admin.json").read_text())
    assert admin["file_format"] == ["csv"] and admin["schema_version"].endswith("admin-schema.json")

    schema = json.loads((REPO / "hub-config" / "model-metadata-schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    config = SubmissionConfig()
    metadata_path = REPO / "pipeline" / "outputs" / "model_metadata" / f"{config.model_id}.yml"
    metadata = yaml.safe_load(metadata_path.read_text())
    jsonschema.validate(metadata, schema)
    assert f"{metadata['team_abbr']}-{metadata['model_abbr']}" == config.model_id
    broken = {**metadata, "license": "proprietary"}
    with pytest.raises(jsonschema.ValidationError, match="is not one of"):
        jsonschema.validate(broken, schema)
    assert model_output_path("hub", REF, config.model_id).as_posix() == \
        "hub/model-output/flowcast-nfens/2022-03-19-flowcast-nfens.csv"
