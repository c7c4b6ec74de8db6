"""The hub's rounds in the engine: the revision nowcast against a known revision ratio, the
weekly flow (valid paths, only the past, a cell's own draws), the seasonal member against hand
-computed growth, top-down reconciliation, and a few real NHSN rounds end to end (read from
``../shared/data/nhsn`` in place, imported as the product imports them): real-time rounds,
hub horizons, the latest vintage as truth, and the round's file valid for the hub and read
back with hubdata."""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
from pipeline.combine.combiner import PUBLISHED
from pipeline.combine.reconcile import median_gap, top_down
from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages
from pipeline.data.hub.target_import import import_hub_time_series
from pipeline.hub_round.run import HUB_PRESETS
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.members.seasonal import SeasonalConfig, SeasonalGrowthMember, seasonal_growth
from pipeline.members.nf.weekly import WeeklyFlowMember
from pipeline.members.nf.flow import train_flow
from pipeline.nowcast.revisions import RevisionNowcastConfig, nowcast_weeks
from pipeline.outputs.hubverse_round import (CDC_HUB_MODEL_ID, compound_sample_ids,
                                             load_model_metadata, write_hub_round)
from pipeline.outputs.hubverse_validation import load_tasks_config
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.hub import HOSP_COVID, hub_rounds, panel_of, reference_date_for
from pipeline.panels.panel import Cells, Panel
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
from tests.forecasting_helpers import forecast_one

REPO = Path(__file__).resolve().parents[1]
NHSN = REPO.parent / "shared" / "data" / "nhsn"
LEVELS = np.asarray(HUB_QUANTILE_LEVELS)
TINY_FLOW = HUB_PRESETS["tiny"].members.flow          # the hub round's smoke preset


def _weekly(values, start: str = "2024-11-09", population: int = 1_000_000,
            target: str = HOSP_COVID) -> WeeklyHistory:
    dates = pd.date_range(start, periods=len(values), freq="7D")
    return WeeklyHistory(dates, np.asarray(values, dtype=float), population, target)


def test_revision_nowcast_learns_the_ratio_of_earlier_vintages():
    """Every vintage reports its newest week at 80 % of the value the next vintage holds: the
    nowcast's median of a new vintage's newest week is the reported value / 0.8 (on log(1+x)),
    and a week already revised (lag 1) is left as it is."""
    final = 1000.0 + 50.0 * np.arange(20)
    vintages = []
    for end in range(6, 20):
        values = final[:end].copy()
        values[-1] *= 0.8
        vintages.append(Panel({p: _weekly(values * (1 + k)) for k, p in enumerate(("01", "02"))},
                              as_of=pd.Timestamp("2024-11-13") + pd.Timedelta(weeks=end)))
    now = nowcast_weeks(vintages[-1], vintages[:-1], LEVELS, RevisionNowcastConfig(lags=2))
    reported = vintages[-1].histories["01"].cases[-1]
    expected = np.expm1(np.log1p(reported) + np.log1p(final[18]) - np.log1p(0.8 * final[18]))
    assert now.quantiles["01"][0, 11] == pytest.approx(expected, rel=2e-3)
    assert now.quantiles["01"][1, 11] == pytest.approx(final[17], rel=1e-9)     # lag 1: final
    # the corrected panel holds the median in place of the reported newest week
    corrected = now.panel.histories["01"].cases
    assert corrected[-1] == pytest.approx(now.quantiles["01"][0, 11])
    np.testing.assert_allclose(corrected[:-1], vintages[-1].histories["01"].cases[:-1], rtol=1e-12)
    # with no earlier vintage there is nothing to learn from: the weeks stay as reported
    alone = nowcast_weeks(vintages[0], [], LEVELS)
    assert alone.quantiles["01"][0, 11] == pytest.approx(vintages[0].histories["01"].cases[-1])


def test_reference_dates_of_releases():
    assert reference_date_for(pd.Timestamp("2024-11-20")) == pd.Timestamp("2024-11-23")  # Wed
    assert reference_date_for(pd.Timestamp("2024-12-26")) == pd.Timestamp("2024-12-28")  # Thu
    assert reference_date_for(pd.Timestamp("2025-01-03")) == pd.Timestamp("2025-01-11")  # Fri


@pytest.fixture(scope="module")
def flow() -> WeeklyFlowMember:
    estimator, _ = train_flow(TINY_FLOW)
    return WeeklyFlowMember(estimator, TINY_FLOW, n_samples=200)


def test_weekly_flow_forecasts_are_valid_and_see_only_the_past(flow: WeeklyFlowMember):
    rng = np.random.default_rng(0)
    history = _weekly(rng.poisson(np.linspace(200, 900, 30)))
    origin = history.dates[19]
    a = forecast_one(flow, history.up_to(origin), (1, 2, 3, 4, 5), seed=4)
    altered = dataclasses.replace(history, cases=np.where(np.arange(30) > 19,
                                                          history.cases * 10, history.cases))
    b = forecast_one(flow, altered.up_to(origin), (1, 2, 3, 4, 5), seed=4)
    q = a.values[HOSP_COVID]
    assert q.shape == (5, 23) and (q >= 0).all() and (np.diff(q, axis=1) >= 0).all()
    np.testing.assert_array_equal(q, b.values[HOSP_COVID])
    # a two-week series (the hub's first round) is forecast from its masked context
    short = forecast_one(flow, history.up_to(history.dates[1]), (1,), seed=4)
    assert np.isfinite(short.values[HOSP_COVID]).all()
    # a cell's draws are its own: in a batch with another cell, the same numbers
    alone = flow.sample_paths([history.up_to(origin)], [4])
    both = flow.sample_paths([history.up_to(history.dates[10]), history.up_to(origin)], [9, 4])
    np.testing.assert_allclose(both[1], alone[0], rtol=1e-5)
    # a rate (the ED share per 100,000 visits) leaves S at 1: shares below 100 %
    rate = dataclasses.replace(history.up_to(origin), population=100_000, depletes=False,
                               cases=history.up_to(origin).cases * 10.0)
    paths = flow.sample_paths([rate], [1])[0]
    assert (paths[..., 1] > 0).all() and (paths[..., 1] < 1).all()


def test_seasonal_growth_is_the_pooled_past_growth_at_this_time_of_year():
    """A climatology that doubles from ISO week 40 to 41 and is flat otherwise, two seasons
    back: at an origin in week 40 the one-step growth quantiles are log 2 (pooled over two
    places × the ±0-week band of two earlier years)."""
    dates = pd.date_range("2022-10-01", "2025-10-04", freq="7D")
    weeks = np.asarray(dates.isocalendar().week)
    level = np.cumsum(np.where(weeks == 41, np.log(2.0), 0.0))
    values = np.expm1(np.log1p(100.0) + level)
    panel = Panel({p: WeeklyHistory(dates, values * (k + 1), 100_000, "x") for k, p in
                   enumerate(("a", "b"))})
    origin = dates[np.flatnonzero(weeks == 40)[-1]]
    growth = seasonal_growth(panel, origin, (1,), LEVELS, SeasonalConfig(band=0))
    assert growth[0, 11] == pytest.approx(np.log1p(200.0) - np.log1p(100.0), rel=1e-2)
    member = SeasonalGrowthMember(((pd.Timestamp("2025-10-08"), panel),), SeasonalConfig(band=0))
    own = _weekly([50.0, 60.0], start=str((origin - pd.Timedelta(weeks=1)).date()))
    early = Panel({"x": own}, as_of=pd.Timestamp("2025-10-01"))
    later = dataclasses.replace(early, as_of=pd.Timestamp("2025-10-09"))
    cells = Cells.of([own, own], [0, 0], ["x", "x"], [early, later])
    made = member.forecast(cells, (1,), LEVELS).count
    assert np.isnan(made[0]).all()              # no climatology released by the first's date
    assert made[1, 0, 11] == pytest.approx(np.expm1(np.log1p(60.0) + growth[0, 11]))


def test_top_down_makes_the_states_medians_sum_to_the_national_one():
    rng = np.random.default_rng(2)
    places = ("US", "01", "02", "06")
    q = np.sort(rng.gamma(3.0, 100.0, size=(4, 3, 2, 23)), axis=-1)
    q[0] *= 3.0
    out = top_down(q, places, "US", LEVELS)
    np.testing.assert_allclose(out[1:, ..., 11].sum(axis=0), out[0, ..., 11], rtol=1e-12)
    np.testing.assert_array_equal(out[0], q[0])
    assert (np.diff(out, axis=-1) >= 0).all()
    np.testing.assert_allclose(median_gap(out, places, "US", LEVELS), 0.0, atol=1e-12)


def test_the_states_are_reconciled_only_where_that_scored_better_then():
    """Two versions of a forecast of 10 at every place: at step 1 the plain one is exact and
    the reconciled one off by 10; at step 2 which is exact depends on the truth as known at the
    origin (10 before the fifth origin, revised to 20 from it). Each origin takes the one that
    scored better on the outcomes its own truth held, the reconciled one while none was known."""
    from pipeline.combine.reconcile import reconciled_where_better

    origins = list(pd.date_range("2025-01-04", periods=6, freq="7D"))
    levels = np.array([0.25, 0.5, 0.75])
    plain = np.full((3, 6, 2, 3), 10.0)
    reconciled = plain.copy()
    reconciled[1:, :, 0] = 20.0                    # step 1: the states pulled off the truth
    reconciled[1:, :, 1] = 20.0                    # step 2: exact once the truth is revised
    baseline = np.full_like(plain, 10.0) + np.array([-5.0, 0.0, 5.0])

    def truth_at(j: int) -> np.ndarray:
        return np.full((3, 6, 2), 10.0 if j < 4 else 20.0)
    out, chosen = reconciled_where_better(plain, reconciled, baseline, truth_at, origins,
                                          (1, 2), levels)
    assert chosen[:, 0].tolist() == [True, False, False, False, True, True]
    assert chosen[:, 1].tolist() == [True, True, False, False, True, True]
    np.testing.assert_array_equal(out[:, 2, 0], plain[:, 2, 0])
    np.testing.assert_array_equal(out[:, 5, 1], reconciled[:, 5, 1])


@pytest.fixture(scope="module")
def real_vintages(tmp_path_factory) -> list:
    if not (NHSN / "time-series.parquet").exists():
        pytest.fail(f"the hub's target data are expected at {NHSN} (../shared beside the repo)")
    root = tmp_path_factory.mktemp("nhsn-data")
    import_hub_time_series(NHSN, root)
    return [(v.as_of, panel_of(v)) for v in cached_weekly_vintages(HOSP_COVID, root)]


def test_real_rounds_in_real_time_and_the_round_file(real_vintages, tmp_path):
    """The first eight admissions rounds of the hub's data, forecast by the hub baseline from
    each round's own vintage: origins, horizons, the nowcast week, the latest vintage as truth,
    and the newest round's file valid against the hub's tasks.json, read back by hubdata."""
    import hubdata

    assert len(real_vintages) == 44
    rounds = hub_rounds(real_vintages[:8])
    assert [str(r.reference.date()) for r in rounds[:2]] == ["2024-11-23", "2024-11-30"]
    assert rounds[0].origin == pd.Timestamp("2024-11-16") and rounds[0].lag_weeks == 1
    latest = real_vintages[-1][1]
    result = run_hub_rounds(rounds, latest, [HubBaseline(HubBaselineConfig(n_samples=2000))],
                            HubBacktestConfig())
    assert len(result.places) == 53 and result.horizons == (-1, 0, 1, 2, 3)
    pa = result.places.index("42")
    # Pennsylvania's week ending 2024-11-16 as the latest vintage holds it is the truth of
    # the first round's horizon -1 (reported 6,124 in the round's own vintage, then revised)
    assert rounds[0].panel.histories["42"].cases[-1] == 6124.0
    assert result.truth.values[pa, 0, 0] == latest.histories["42"].cases[1]
    assert result.truth.values[pa, 0, 0] != 6124.0
    # the published forecast at horizon -1 is the nowcast of the reported week
    np.testing.assert_array_equal(result.forecasts[PUBLISHED].values[:, 0, 0],
                                  np.stack([result.nowcasts[0].quantiles[p][0]
                                            for p in result.places]))
    assert np.isfinite(result.forecasts[PUBLISHED].values[:, :, 1:]).all()
    # the one summary of every backtest, at the forecast horizons, by phase of the epidemic
    summary = result.summary(PUBLISHED, (0, 1))
    phases = [summary["by_regime"][r]["n_scored"] for r in ("falling", "flat", "rising")]
    assert sum(phases) == summary["n_scored"] > 0
    covered = result.forecasts[PUBLISHED].select(horizons=(0, 1)).score(
        result.truth.select(horizons=(0, 1))).covered[0.5]
    assert summary["coverage50"] == pytest.approx(float(np.nanmean(covered)), abs=1e-12)
    # the published forecast is held within the bound on falls; the baseline alone goes below
    beyond = result.backtest.plausibility()["share_beyond"]
    assert beyond[PUBLISHED] == 0.0 and beyond["hub-baseline"] > 0.01
    frame = compound_sample_ids(result.round_frame(len(rounds) - 1))
    root = tmp_path / "hub"
    shutil.copytree(NHSN / "hub-config", root / "hub-config")
    written = write_hub_round(frame, hub_dir=root, model_id=CDC_HUB_MODEL_ID,
                              tasks=load_tasks_config(NHSN / "hub-config" / "tasks.json"),
                              metadata=load_model_metadata(REPO / "pipeline" / "outputs" / "model_metadata"
                                                           / f"{CDC_HUB_MODEL_ID}.yml"))
    back = hubdata.connect_hub(root).get_dataset().to_table().to_pandas()
    assert len(back) == 53 * 5 * (23 + 200) and set(back.location) == set(result.places)
    assert written.reference_date == rounds[-1].reference.date()
    # `python -m bench.nhsn --files DIR` writes every round's file (issue 37)
    from bench.nhsn import write_round_files

    files = tmp_path / "files"
    shutil.copytree(NHSN / "hub-config", files / "hub-config")
    assert write_round_files({HOSP_COVID: result}, files, NHSN) == 8
    every = hubdata.connect_hub(files).get_dataset().to_table().to_pandas()
    assert sorted(every["reference_date"].astype(str).unique()) == [
        str(r.reference.date()) for r in rounds]
    assert len(every) == 8 * 53 * 5 * (23 + 200)


def test_the_reconciled_forecast_is_held_within_the_bound_on_falls(real_vintages, monkeypatch):
    """A reconciliation that pulls every state's quantiles down to a tenth (as a national
    forecast far below the states' sum would): the published forecast is held at its bound
    again after it, where the same reconciliation without the bound goes below it."""
    import pipeline.backtest.hub_rounds as engine

    def collapsing(values, places, national, levels):
        states = np.array([p != national for p in places])
        return np.where(states[:, None, None, None], 0.1 * values, values)

    monkeypatch.setattr(engine, "top_down", collapsing)
    rounds = hub_rounds(real_vintages[:3])
    result = run_hub_rounds(rounds, real_vintages[-1][1],
                            [HubBaseline(HubBaselineConfig(n_samples=200))],
                            HubBacktestConfig(burn_in_weeks=0, n_samples=0,
                                              reconcile="always"))
    held = result.backtest
    lower = np.nan_to_num(held.bounds[..., 0], nan=-np.inf)     # NaN: no bound there
    published = held.forecasts[held.panel.count_target][PUBLISHED].values
    unreconciled = held.forecasts[held.panel.count_target]["published-unreconciled"].values
    assert held.plausibility()["share_beyond"][PUBLISHED] == 0.0
    assert (published >= lower[..., None]).all()
    pulled = 0.1 * unreconciled
    assert (pulled < lower[..., None]).mean() > 0.1          # the reconciliation went below
    np.testing.assert_array_equal(published, np.maximum(np.where(
        np.array([p != "US" for p in held.places])[:, None, None, None], pulled, unreconciled),
        lower[..., None]))
    # reconciled only where that scored better: the first round (nothing scored yet) and the
    # steps not yet scored; not once its first step has been scored
    better = run_hub_rounds(rounds, real_vintages[-1][1],
                            [HubBaseline(HubBaselineConfig(n_samples=200))],
                            HubBacktestConfig(burn_in_weeks=0, n_samples=0))
    assert better.reconciled is not None
    np.testing.assert_array_equal(better.reconciled, np.triu(np.ones((3, 4), dtype=bool)))


def test_the_combiner_learns_from_each_rounds_vintage_not_later_revisions(real_vintages):
    """Ten admissions rounds scored against two later releases that revised their weeks: each
    round's weights and calibration come from the outcomes its own vintage held (its newest
    weeks at their nowcast), so every round's published forecast is the same whichever release
    is the truth (learning from the final values, it was not: the backtest's leak)."""
    from pipeline.backtest.backtest import Vintages
    from pipeline.combine.combiner import UNCALIBRATED

    rounds = hub_rounds(real_vintages[:10])
    members = [HubBaseline(HubBaselineConfig(n_samples=1000)),
               HubBaseline(HubBaselineConfig(n_samples=500), name="other")]
    config = HubBacktestConfig(burn_in_weeks=0, n_samples=0)
    early, final = (run_hub_rounds(rounds, real_vintages[k][1], members, config)
                    for k in (10, -1))
    revised = np.isfinite(early.truth.values) & (early.truth.values != final.truth.values)
    assert revised.sum() > 50                              # the releases disagree on the truth
    for name in (PUBLISHED, UNCALIBRATED):
        np.testing.assert_array_equal(early.forecasts[name].values, final.forecasts[name].values)
    learnt = final.forecasts[PUBLISHED].values[:, -1, 2:] - final.forecasts[UNCALIBRATED].values[
        :, -1, 2:]
    assert np.abs(learnt).max() > 0                        # the calibration did move them
    # origin j's truth: its vintage's values before j, nothing at or after it
    vintages = Vintages(Panel({p: real_vintages[-1][1].histories[p] for p in ("01", "US")}),
                        [rounds[0].panel, rounds[1].panel])
    at = vintages.truth_known([rounds[0].origin, rounds[1].origin], (1,))
    assert np.isnan(at(0)).all() and np.isnan(at(1)[:, 1]).all()
    np.testing.assert_array_equal(at(1)[:, 0, 0], [rounds[1].panel.histories[p].cases[-1]
                                                   for p in ("01", "US")])


def test_each_hub_target_averages_its_own_members():
    from pipeline.members.published import HubMembersConfig, published_names
    from pipeline.panels.hub import ED_COVID, HOSP_COVID
    config = HubMembersConfig()
    # admissions, every hub: the context flow and gbqr (the weekly flow and the seasonal
    # member scored beside them; bench/results/nhsn.json, flusight.json)
    assert published_names(config, HOSP_COVID, refitted=True) == ("nf-context", "gbqr")
    assert published_names(config, HOSP_COVID, refitted=True, own_seasons=True) == (
        "nf-context", "gbqr")
    # the share's average takes the context flow (its pre-trained model serves before a refit)
    assert published_names(config, ED_COVID, refitted=True) == ("nf-context", "seasonal")
    assert published_names(config, ED_COVID, refitted=False) == ("nf-context", "seasonal")
    # an average with nf-real takes the weekly flow before the first refit, never nothing
    real = HubMembersConfig(published_share=("nf-real", "seasonal"))
    assert published_names(real, ED_COVID, refitted=False) == ("nf-weekly", "seasonal")
    both = HubMembersConfig(published_share=("nf-real", "nf-weekly", "seasonal"))
    assert published_names(both, ED_COVID, refitted=False) == ("nf-weekly", "seasonal")


def test_gbqr_reads_the_other_signal_of_its_target():
    """Admissions' gbqr reads the ED share (the climatology), the share's reads admissions (the
    other signal given), influenza's (its own seasons, no ED vintage) none."""
    from pipeline.members.published import other_signal_of
    from pipeline.panels.hub import ED_COVID, HOSP_COVID
    ed = ((pd.Timestamp("2025-06-18"), Panel({"01": _weekly([1.0, 2.0])}, name="ed")),)
    hosp = ((pd.Timestamp("2025-06-18"), Panel({"01": _weekly([3.0, 4.0])}, name="hosp")),)
    assert other_signal_of(HOSP_COVID, ed, None, own_seasons=False) == ed
    assert other_signal_of(ED_COVID, ed, hosp, own_seasons=False) == hosp
    assert other_signal_of(ED_COVID, ed, None, own_seasons=False) == ()
    assert other_signal_of(HOSP_COVID, (), None, own_seasons=True) == ()


@dataclasses.dataclass
class _Recorder:
    """The hub baseline, recording the origins and vintages of the cells it forecasts."""

    member: HubBaseline
    seen: list = dataclasses.field(default_factory=list)

    @property
    def name(self) -> str:
        return self.member.name

    def forecast(self, cells: Cells, horizons, levels):
        self.seen += [(o, p.as_of, p.last_date) for o, p in zip(cells.origins, cells.panels)]
        return self.member.forecast(cells, horizons, levels)


@pytest.fixture(scope="module")
def ed_vintages(tmp_path_factory) -> list:
    from pipeline.panels.hub import ED_COVID

    root = tmp_path_factory.mktemp("nhsn-ed")
    import_hub_time_series(NHSN, root)
    return [(v.as_of, panel_of(v)) for v in cached_weekly_vintages(ED_COVID, root)]


def test_the_burn_in_teaches_the_calibration_from_the_first_vintage_alone(real_vintages,
                                                                          ed_vintages):
    """Eight weeks before the first round are forecast from the first round's vintage cut at
    each (nothing later), not reported, and their outcomes move the online calibration: the
    first rounds' average is the same, their published intervals are not. Admissions' first
    release holds two weeks (from 2024-11-09): no burn-in there; the ED share's, since
    2022-10."""
    from pipeline.backtest.hub_rounds import burn_in_origins
    from pipeline.combine.combiner import UNCALIBRATED

    assert burn_in_origins(hub_rounds(real_vintages[:1])[0].panel, 52) == []
    rounds = hub_rounds(ed_vintages[:3])
    first = rounds[0].panel
    assert first.first_date == pd.Timestamp("2022-10-01")
    assert len(burn_in_origins(first, 52)) == 52
    origins = burn_in_origins(first, 8)
    assert origins == [first.last_date - pd.Timedelta(weeks=k) for k in range(8, 0, -1)]
    # a place with 9 weeks of data before the first origin allows one burn-in week
    late = Panel({"01": _weekly(np.arange(10.0) + 5, start=str(
        (first.last_date - pd.Timedelta(weeks=9)).date()))}, as_of=first.as_of)
    assert burn_in_origins(late, 8) == [first.last_date - pd.Timedelta(weeks=1)]
    # a week one place did not report is no burn-in origin (the flows need the origin's week)
    gap = np.arange(20.0) + 5
    gap[-4] = np.nan
    holed = Panel({"01": _weekly(np.arange(20.0) + 5, start=str(
        (first.last_date - pd.Timedelta(weeks=19)).date())), "02": _weekly(gap, start=str(
            (first.last_date - pd.Timedelta(weeks=19)).date()))}, as_of=first.as_of)
    assert burn_in_origins(holed, 8) == [first.last_date - pd.Timedelta(weeks=k)
                                         for k in (8, 7, 6, 5, 4, 2, 1)]
    latest = ed_vintages[-1][1]
    results = {}
    for weeks in (0, 8):
        recorder = _Recorder(HubBaseline(HubBaselineConfig(n_samples=2000)))
        results[weeks] = run_hub_rounds(rounds, latest, [recorder],
                                        HubBacktestConfig(burn_in_weeks=weeks))
        burn = [s for s in recorder.seen if s[0] < rounds[0].origin]
        assert sorted({s[0] for s in burn}) == (origins if weeks else [])
        # each burn-in cell sees the first round's vintage, cut at its own origin
        assert all(as_of == rounds[0].as_of and last <= o for o, as_of, last in burn)
    without, with_burn_in = results[0], results[8]
    assert with_burn_in.references == without.references
    np.testing.assert_array_equal(with_burn_in.forecasts[UNCALIBRATED].values,
                                  without.forecasts[UNCALIBRATED].values)
    assert not np.array_equal(with_burn_in.forecasts[PUBLISHED].values[:, 0, 1:],
                              without.forecasts[PUBLISHED].values[:, 0, 1:])
    # the median is never moved by the calibration
    np.testing.assert_allclose(with_burn_in.forecasts[PUBLISHED].median(),
                               without.forecasts[PUBLISHED].median(), rtol=1e-9)
