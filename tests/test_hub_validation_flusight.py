"""The hubverse validator on real hubs: FluSight's own ``tasks.json`` (one round definition of
five model tasks: weekly admissions with integer samples, the rate-change pmf, the peak's
quantiles and week pmf with no horizon, the ED share bounded by 1) and a hub of several round
definitions; each output type's rules refused by name. Read in place from ``../shared``."""
from __future__ import annotations

import copy
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

from pipeline.outputs.hub_tasks import (has_round, hub_round_ids, output_rules,
                                        target_model_task)
from pipeline.outputs.hubverse_validation import (HubValidationError, hub_columns,
                                                  load_tasks_config,
                                                  validate_model_output_frame)
from pipeline.panels.targets import HUB_QUANTILE_LEVELS, format_level

REPO = Path(__file__).resolve().parents[1]
FLUSIGHT = REPO.parent / "shared" / "data" / "flusight" / "hub-config"
NHSN = REPO.parent / "shared" / "data" / "nhsn" / "hub-config"
REFERENCE = "2025-12-06"           # a 2025-26 round: the peak week's categories are its weeks
LOCATIONS = ("US", "06")
HOSP, RATE, PEAK, PEAK_WEEK, ED = ("wk inc flu hosp", "wk flu hosp rate change",
                                   "peak inc flu hosp", "peak week inc flu hosp",
                                   "wk inc flu prop ed visits")
CATEGORIES = ("large_decrease", "decrease", "stable", "increase", "large_increase")


@pytest.fixture(scope="module")
def tasks() -> dict:
    return load_tasks_config(FLUSIGHT / "tasks.json")


def _end(horizon: int) -> str:
    return str((pd.Timestamp(REFERENCE) + pd.Timedelta(weeks=horizon)).date())


def _rows(target: str, kind: str, ids: list[str], values: np.ndarray, horizons: list[int] | None
          ) -> pd.DataFrame:
    """Text rows of one target × output type for every location and horizon (None: a peak
    target, horizon and target end date NA); ``values`` ``(L, H or 1, len(ids))``."""
    hs = horizons or [None]
    index = pd.MultiIndex.from_product([LOCATIONS, range(len(hs)), ids],
                                       names=["location", "h", "output_type_id"]).to_frame(
        index=False)
    horizon = np.asarray(hs, dtype=object)[index.h]
    return pd.DataFrame({
        "reference_date": REFERENCE, "target": target,
        "horizon": ["" if h is None else str(h) for h in horizon],
        "location": index.location,
        "target_end_date": ["" if h is None else _end(h) for h in horizon],
        "output_type": kind, "output_type_id": index.output_type_id,
        "value": [f"{v:.8g}" for v in np.asarray(values, dtype=float).reshape(-1)]})


def flusight_round(n_samples: int = 100, ed_scale: float = 0.02) -> pd.DataFrame:
    """Every FluSight target for two locations, as text cells (a CSV read with ``dtype=str``):
    log-normal admissions (median 100·(1 + h/10)), their integer sample paths, a rate-change
    pmf, the peak's quantiles and week pmf, the ED share's quantiles and samples."""
    rng = np.random.default_rng(0)
    hs = [-1, 0, 1, 2, 3]
    levels = [format_level(q) for q in HUB_QUANTILE_LEVELS]
    z = norm.ppf(HUB_QUANTILE_LEVELS)
    median = 100.0 * (1 + np.asarray(hs) / 10)
    q = median[None, :, None] * np.exp(0.3 * z)[None, None, :] * np.ones((2, 1, 1))
    # one id per path of a location (its compound task), the same id across the horizons
    paths = np.round(median[None, None, :] * np.exp(0.3 * rng.standard_normal((2, n_samples,
                                                                                1))))
    samples = pd.DataFrame({
        "reference_date": REFERENCE, "target": HOSP,
        "horizon": np.tile([str(h) for h in hs], 2 * n_samples),
        "location": np.repeat(LOCATIONS, n_samples * len(hs)),
        "target_end_date": np.tile([_end(h) for h in hs], 2 * n_samples),
        "output_type": "sample",
        "output_type_id": np.repeat(np.arange(2 * n_samples), len(hs)).astype(str),
        "value": [f"{v:.8g}" for v in paths.reshape(-1)]})
    pmf = np.array([0.1, 0.2, 0.4, 0.2, 0.1])
    weeks = [str(d.date()) for d in pd.date_range("2025-11-22", "2026-05-23", freq="7D")]
    week_pmf = np.full(len(weeks), 1.0 / len(weeks))
    return pd.concat([
        _rows(HOSP, "quantile", levels, q, hs), samples,
        _rows(RATE, "pmf", list(CATEGORIES), np.tile(pmf, (2, 4, 1)), [0, 1, 2, 3]),
        _rows(PEAK, "quantile", levels, 300.0 * np.exp(0.4 * z)[None, None, :] * np.ones(
            (2, 1, 1)), None),
        _rows(PEAK_WEEK, "pmf", weeks, np.tile(week_pmf, (2, 1, 1)), None),
        _rows(ED, "quantile", levels, ed_scale * np.exp(0.3 * z) * np.ones((2, 5, 1)), hs),
    ], ignore_index=True)[hub_columns(load_tasks_config(FLUSIGHT / "tasks.json"))]


def test_flusights_rules_are_read_from_its_own_config(tasks):
    assert hub_columns(tasks) == ["reference_date", "target", "horizon", "location",
                                  "target_end_date", "output_type", "output_type_id", "value"]
    rounds = hub_round_ids(tasks)
    assert (len(rounds), rounds[0], rounds[-1]) == (89, "2023-10-07", "2026-05-30")
    assert not has_round(tasks, pd.Timestamp("2026-07-04").date())     # off season: no round
    assert has_round(tasks, pd.Timestamp(REFERENCE).date())
    day = pd.Timestamp(REFERENCE).date()
    hosp = output_rules(target_model_task(tasks, day, HOSP))
    assert (hosp.n_samples, hosp.values["sample"].integer, hosp.values["quantile"].integer) \
        == (100, True, False)
    assert hosp.compound == ("reference_date", "location", "target")
    ed = output_rules(target_model_task(tasks, day, ED))
    assert (ed.values["quantile"].maximum, ed.values["sample"].integer) == (1, False)
    assert output_rules(target_model_task(tasks, day, PEAK)).horizons == ()
    rate = output_rules(target_model_task(tasks, day, RATE))
    assert rate.output_type_ids["pmf"] == CATEGORIES
    covid = load_tasks_config(NHSN / "tasks.json")
    assert output_rules(target_model_task(covid, pd.Timestamp("2025-10-18").date(),
                                          "wk inc covid hosp")).n_samples == 200


def test_a_round_of_every_flusight_target_is_valid_and_typed(tasks, tmp_path):
    frame = flusight_round()
    typed = validate_model_output_frame(frame, tasks)
    assert len(typed) == len(frame) == 2 * (5 * 23 + 100 * 5 + 4 * 5 + 23 + 27 + 5 * 23)
    assert str(typed["horizon"].dtype) == "Int64"               # NA for the peak targets
    peak = typed[typed.target == PEAK]
    assert peak.horizon.isna().all() and peak.target_end_date.isna().all()
    assert typed.loc[typed.output_type == "sample", "value"].eq(
        typed.loc[typed.output_type == "sample", "value"].round()).all()
    # and the hubverse's own reader takes the file
    import hubdata
    root = tmp_path / "hub"
    shutil.copytree(FLUSIGHT, root / "hub-config")
    folder = root / "model-output" / "flowcast-nfhub"
    folder.mkdir(parents=True)
    frame.to_csv(folder / f"{REFERENCE}-flowcast-nfhub.csv", index=False)
    back = hubdata.connect_hub(root).get_dataset().to_table().to_pandas()
    assert len(back) == len(frame)
    assert back.groupby("target").size().to_dict() == frame.groupby("target").size().to_dict()


def _set(frame: pd.DataFrame, where: pd.Series, column: str, value: str) -> pd.DataFrame:
    out = frame.copy()
    out.loc[where, column] = value
    return out


def _first(frame: pd.DataFrame, target: str, kind: str) -> pd.Series:
    hit = (frame.target == target) & (frame.output_type == kind)
    return hit & (hit.cumsum() == 1)


# the breaks the issue found in the product's FluSight rounds, and each output type's rules
BROKEN = [
    (lambda f: flusight_round(n_samples=200),
     r"200 samples for compound task \{'reference_date': '2025-12-06', 'location': '06', "
     r"'target': 'wk inc flu hosp'\}; the hub asks for 100\.\.100"),
    (lambda f: _set(f, _first(f, HOSP, "sample"), "value", "1027.8882"),
     r"column 'value': 1027\.8882 is not of type 'integer'"),
    (lambda f: _set(f, _first(f, ED, "quantile"), "value", "115.7"),
     r"column 'value': 115\.7 is greater than the maximum of 1"),
    (lambda f: f.assign(reference_date="2026-07-04"),
     r"column 'reference_date': '2026-07-04' is not a round of the hub \(89 rounds, "
     r"2023-10-07 … 2026-05-30\)"),
    (lambda f: _set(f, _first(f, HOSP, "quantile"), "target_end_date", "2027-01-02"),
     r"column 'target_end_date': '2027-01-02' is not one of"),
    (lambda f: _set(f, _first(f, RATE, "pmf"), "value", "0.5"),
     r"pmf task .*target=wk flu hosp rate change.* sums to 1\.4, not 1"),
    (lambda f: f[~(_first(f, RATE, "pmf"))],
     r"pmf task .* lacks the categories \['large_decrease'\]"),
    (lambda f: _set(f, _first(f, RATE, "pmf"), "output_type_id", "flat"),
     r"column 'output_type_id': 'flat' is not one of"),
    (lambda f: _set(f, _first(f, RATE, "pmf"), "output_type", "quantile"),
     r"output_type 'quantile' is not one of \['pmf'\]"),
    (lambda f: _set(f, _first(f, PEAK, "quantile"), "horizon", "1"),
     r"column 'horizon': '1' is not of type 'null'"),
    (lambda f: _set(f, _first(f, PEAK_WEEK, "pmf"), "output_type_id", "2024-12-07"),
     r"column 'output_type_id': '2024-12-07' is not one of"),
    (lambda f: _set(f, _first(f, PEAK_WEEK, "pmf"), "value", "1.5"),
     r"1\.5 is greater than the maximum of 1"),
    (lambda f: _set(f, _first(f, HOSP, "quantile"), "target", "wk inc flu death"),
     r"column 'target': 'wk inc flu death' is not one of"),
]


@pytest.mark.parametrize("mutate, match", BROKEN)
def test_each_rule_of_flusights_config_is_refused_by_name(tasks, mutate, match):
    with pytest.raises(HubValidationError, match=match):
        validate_model_output_frame(mutate(flusight_round()), tasks)


def test_several_round_definitions_each_by_its_own_rules(tasks):
    """A hub whose rules changed between seasons (two round definitions): a round is checked by
    the definition holding its reference date."""
    two = copy.deepcopy(tasks)
    later = copy.deepcopy(tasks["rounds"][0])
    dates = hub_round_ids(tasks)
    split = dates.index("2025-11-22")
    for round_def, keep in ((two["rounds"][0], dates[:split]), (later, dates[split:])):
        for model_task in round_def["model_tasks"]:
            model_task["task_ids"]["reference_date"]["optional"] = keep
    for model_task in later["model_tasks"]:
        sample = model_task["output_type"].get("sample")
        if sample:
            sample["output_type_id_params"]["min_samples_per_task"] = 50
            sample["output_type_id_params"]["max_samples_per_task"] = 50
    two["rounds"].append(later)
    assert len(validate_model_output_frame(flusight_round(n_samples=50), two)) > 0
    with pytest.raises(HubValidationError, match=r"100 samples .*asks for 50\.\.50"):
        validate_model_output_frame(flusight_round(n_samples=100), two)


def _metadata() -> dict:
    from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID, load_model_metadata
    return load_model_metadata(REPO / "pipeline" / "outputs" / "model_metadata" / f"{CDC_HUB_MODEL_ID}.yml")


def test_the_round_follows_flusights_config_not_the_products_constants(tasks, tmp_path):
    """200 paths of non-integer admissions and an ED-share quantile of 115.7 (the breaks the
    issue found) are written as FluSight asks: 100 integer paths a location, the share at most
    1, each change named; the file is valid and read back by hubdata."""
    import hubdata

    from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID, write_hub_round
    frame = flusight_round(n_samples=200)
    samples = (frame.output_type == "sample").to_numpy()
    frame.loc[samples, "value"] = (frame.loc[samples, "value"].astype(float) + 0.4).map(str)
    blown = (frame.target == ED) & (frame.output_type_id == "0.99")
    frame.loc[blown, "value"] = "115.7"
    root = tmp_path / "hub"
    shutil.copytree(FLUSIGHT, root / "hub-config")
    written = write_hub_round(frame, hub_dir=root, model_id=CDC_HUB_MODEL_ID, tasks=tasks,
                              metadata=_metadata())
    back = written.frame
    s = back[back.output_type == "sample"]
    assert s.groupby("location").output_type_id.nunique().tolist() == [100, 100]
    # the kept ids are the first 100 of each location, every horizon of each kept
    assert sorted(s[s.location == "US"].output_type_id.astype(int).unique()) == list(range(100))
    assert s.groupby("output_type_id").horizon.nunique().eq(5).all()
    assert (s.value == s.value.round()).all()
    original = frame[samples & (frame.location == "US") & (frame.output_type_id == "7")]
    np.testing.assert_array_equal(
        s[(s.location == "US") & (s.output_type_id == "7")].sort_values("horizon").value,
        np.round(original.value.astype(float).to_numpy()))
    ed = back[back.target == ED]
    assert ed.value.max() == 1.0
    assert written.notes == (f"{ED}: 10 quantile values above the hub's bound 1 (the largest "
                             "115.7) set to it",)
    peak = back[back.target == PEAK]
    assert peak.horizon.isna().all() and len(peak) == 2 * 23
    table = hubdata.connect_hub(root).get_dataset().to_table().to_pandas()
    assert len(table) == len(back) == len(flusight_round(n_samples=100))


def test_no_round_off_season_and_no_file(tasks, tmp_path):
    from pipeline.outputs.hub_conform import NoHubRoundError
    from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID, write_hub_round
    root = tmp_path / "hub"
    with pytest.raises(NoHubRoundError, match=r"takes no round for the reference date "
                       r"2026-07-04 \(89 rounds, 2023-10-07 … 2026-05-30\): no round written"):
        write_hub_round(flusight_round().assign(reference_date="2026-07-04"), hub_dir=root,
                        model_id=CDC_HUB_MODEL_ID, tasks=tasks, metadata=_metadata())
    assert not root.exists()


def test_derived_targets_rows_are_flusights(tasks, tmp_path):
    """The rate change and the peak of a round as derive_targets lays them out: valid for
    FluSight's config in 2025-26, whose peak-week categories are that season's weeks; a round
    of an earlier season writes no peak (the config has no category for its weeks)."""
    from pipeline.outputs.derived_round import DerivedTargets, derived_round_frame
    from pipeline.outputs.derived_targets import season_weeks
    from pipeline.outputs.hub_tasks import task_values
    from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID, write_hub_round

    def targets(reference: str) -> DerivedTargets:
        ref = pd.Timestamp(reference)
        levels = np.asarray(HUB_QUANTILE_LEVELS)
        return DerivedTargets(
            places=LOCATIONS, references=(ref,), levels=levels,
            rate=np.full((2, 1, 4, 5), 0.2), rate_climatology=np.full((2, 1, 4, 5), 0.2),
            rate_observed=np.zeros((2, 1, 4), dtype=np.int64),
            peak=np.tile(300 * np.exp(norm.ppf(levels)), (2, 1, 1)),
            peak_climatology=np.full((2, 1, 23), np.nan), peak_observed=np.full((2, 1), np.nan),
            peak_week=np.full((2, 1, 27), 1 / 27), peak_week_climatology=np.full((2, 1, 27),
                                                                                 np.nan),
            peak_week_observed=np.full((2, 1), -1), seasons=(season_weeks(ref),))

    model_task = next(t for t in tasks["rounds"][0]["model_tasks"]
                      if t["task_ids"]["target"]["optional"] == [PEAK_WEEK])
    weeks = [str(v) for v in task_values(model_task["output_type"]["pmf"]["output_type_id"])]
    frame = derived_round_frame(targets(REFERENCE), 0, weeks)
    assert frame.groupby("target").size().to_dict() == {RATE: 2 * 4 * 5, PEAK: 2 * 23,
                                                        PEAK_WEEK: 2 * 27}
    written = write_hub_round(frame, hub_dir=tmp_path, model_id=CDC_HUB_MODEL_ID, tasks=tasks,
                              metadata=_metadata())
    assert written.frame[written.frame.target == PEAK].horizon.isna().all()
    earlier = derived_round_frame(targets("2024-12-07"), 0, weeks)
    assert set(earlier.target) == {RATE}
