"""Hub CSV: hand-checked quantiles, layout, validation errors, atomic round trip."""
from __future__ import annotations

import datetime as dt

import numpy as np
import pandas as pd
import pytest

from pipeline.forecast_hub import (HUB_COLUMNS, HUB_QUANTILE_LEVELS, HubConfig, HubFormatError,
                                   hub_forecast_frame, read_hub_csv, validate_hub_frame,
                                   write_hub_csv)

REF = dt.date(2022, 3, 14)
DATES = pd.date_range("2022-03-15", periods=28, freq="D")


def _linear_paths(n: int = 201) -> np.ndarray:
    """Path i has S = i/1000, I = i/1000 + day·1e-4, R = 1 - S: quantiles are known exactly."""
    i = np.arange(n, dtype=float)[:, None]
    day = np.arange(28, dtype=float)[None, :]
    s = np.broadcast_to(i / 1000.0, (n, 28))
    inf = i / 1000.0 + day * 1e-4
    return np.stack([s, inf, 1.0 - s], axis=-1)


def test_standard_levels():
    assert len(HUB_QUANTILE_LEVELS) == 23
    assert HUB_QUANTILE_LEVELS[:3] == (0.01, 0.025, 0.05)
    assert HUB_QUANTILE_LEVELS[-3:] == (0.95, 0.975, 0.99)
    np.testing.assert_allclose(np.diff(HUB_QUANTILE_LEVELS[2:-2]), 0.05)


def test_quantiles_and_samples_hand_checked():
    frame = hub_forecast_frame(_linear_paths(), DATES, REF)
    assert list(frame.columns) == list(HUB_COLUMNS)
    # 4 horizons × 3 targets × (23 quantiles + 200 samples)
    assert len(frame) == 4 * 3 * (23 + 200)
    assert set(frame["location"]) == {"06075"}
    q = frame[frame["output_type"] == "quantile"]
    # 201 values i/1000, i = 0..200: the type-7 quantile at level τ is 200τ/1000 = τ/5.
    s_h1 = q[(q["target"] == "S prop") & (q["horizon"] == 1)]
    np.testing.assert_allclose(s_h1["value"].to_numpy(), np.array(HUB_QUANTILE_LEVELS) / 5)
    # I at horizon 2: target end 2022-03-28 is path step 13 (2022-03-15 + 13 days) -> +0.0013.
    i_h2 = q[(q["target"] == "I prop") & (q["horizon"] == 2)]
    assert set(i_h2["target_end_date"]) == {"2022-03-28"}
    np.testing.assert_allclose(i_h2["value"].to_numpy(), np.array(HUB_QUANTILE_LEVELS) / 5 + 0.0013)
    # R = 1 - S: median 1 - 0.1
    r_h4 = q[(q["target"] == "R prop") & (q["horizon"] == 4)]
    assert r_h4.loc[r_h4["output_type_id"] == "0.5", "value"].item() == pytest.approx(0.9)
    assert set(r_h4["target_end_date"]) == {"2022-04-11"}
    # samples keep the first 200 paths with their index: sample 17 of I at h1 (step 6)
    smp = frame[(frame["output_type"] == "sample") & (frame["target"] == "I prop")
                & (frame["horizon"] == 1)]
    assert smp["output_type_id"].tolist() == [str(k) for k in range(200)]
    assert smp.loc[smp["output_type_id"] == "17", "value"].item() == pytest.approx(0.017 + 6e-4)


def test_round_trip_and_atomic_write(tmp_path):
    frame = hub_forecast_frame(_linear_paths(), DATES, REF)
    path = tmp_path / "hub" / "2022-03-14-flowcast.csv"
    digest = write_hub_csv(frame, path)
    assert len(digest) == 64
    back = read_hub_csv(path)
    assert back["output_type_id"].iloc[1] == "0.025"
    np.testing.assert_allclose(back["value"], frame["value"], rtol=1e-7)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # no temp file left


def test_invalid_frame_is_not_written_and_previous_file_survives(tmp_path):
    good = hub_forecast_frame(_linear_paths(), DATES, REF)
    path = tmp_path / "f.csv"
    write_hub_csv(good, path)
    before = path.read_bytes()
    crossed = good.copy()
    crossed.loc[1, "value"] = -1.0  # level 0.025 of S h1 below level 0.01
    with pytest.raises(HubFormatError, match="S prop horizon 1.*crossing"):
        write_hub_csv(crossed, path)
    assert path.read_bytes() == before


@pytest.mark.parametrize("mutate, match", [
    (lambda f: f.drop(index=3), "quantile levels"),
    (lambda f: f.assign(value=np.where(f.index == 5, np.nan, f["value"])), "missing values"),
    (lambda f: f.assign(output_type=np.where(f.index == 0, "mean", f["output_type"])),
     "output_type"),
    (lambda f: f.assign(target_end_date=np.where(f.index == 0, "2022-03-22", f["target_end_date"])),
     "target_end_date"),
    (lambda f: f.drop(columns="location"), "location"),
])
def test_validation_names_the_problem(mutate, match):
    frame = hub_forecast_frame(_linear_paths(), DATES, REF)
    with pytest.raises(HubFormatError, match=match):
        validate_hub_frame(mutate(frame.copy()))


def test_bad_samples_raise():
    paths = _linear_paths()
    with pytest.raises(HubFormatError, match="NaN"):
        bad = paths.copy()
        bad[3, 4, 1] = np.nan
        hub_forecast_frame(bad, DATES, REF)
    with pytest.raises(HubFormatError, match="200 sample paths"):
        hub_forecast_frame(paths[:50], DATES, REF)
    with pytest.raises(HubFormatError, match="target end dates"):
        hub_forecast_frame(paths[:, :20], DATES[:20], REF)
    with pytest.raises(HubFormatError, match="shape"):
        hub_forecast_frame(paths[..., :2], DATES, REF)
    small = hub_forecast_frame(paths[:20], DATES, REF, HubConfig(n_sample_paths=20,
                                                                 horizons_weeks=(1, 2)))
    assert len(small) == 2 * 3 * (23 + 20)
