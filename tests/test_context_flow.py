"""The context flow (``nf-context``): its channels against hand-computed values, its training
windows cut in real time from the hub's recorded vintages (``../shared/data/nhsn``: the ED share
is unknown to the admissions windows before its first release, and known from it), the decoding
of its paths against the analytic inverse, and the tiny member end to end on real rounds."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
from pipeline.data.hub.locations import POPULATION
from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages
from pipeline.data.hub.target_import import import_hub_time_series
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.errors import TrainingDivergedError
from pipeline.members.nf import context as context_module
from pipeline.members.nf.context import (NF_CONTEXT, TINY_CONTEXT_FLOW, TINY_CONTEXT_REFIT,
                                         TrainingPool, fit_context_member)
from pipeline.members.nf.flow import decode_weekly
from pipeline.members.nf.context_training import refit_windows, synthetic_dataset
from pipeline.members.nf.context_features import (ContextChannels, ContextSources,
                                                  WindowInputs, context_windows,
                                                  fixed_channels, vintage_windows)
from pipeline.members.published import HubMembersConfig, context_channels, context_sources
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.hub import ED_COVID, HOSP_COVID, hub_rounds, panel_of
from pipeline.panels.panel import Cells
from tests.test_hub_engine import NHSN

K, H = 3, 2


def _inputs(series, other) -> WindowInputs:
    return WindowInputs(np.array([series], float), np.array([other], float),
                        np.array(["2025-01-04"], dtype="datetime64[ns]"),
                        np.array([[[0.1, 0.2, 0.4], [0.0, 0.3, 0.5]]]), np.array([1e7]))


def test_channels_are_the_hand_computed_values():
    context, mask = context_windows(_inputs([10, 20, 40], [100, np.nan, 50]), ContextChannels())
    assert context.shape == (1, K, 3 + 3 + 3 + (H + 2) + 1) and mask.all()
    row = context[0]
    np.testing.assert_allclose(row[:, 0], np.log([10.5, 20.5, 40.5]) - np.log(40.5), rtol=1e-6)
    np.testing.assert_allclose(row[:, 1], np.log(40.5) / 10, rtol=1e-6)
    np.testing.assert_allclose(row[:, 2], [-2, -1, 0])
    # the other signal: relative to its latest known week (50), the missing week flagged 0
    np.testing.assert_allclose(row[:, 3], [np.log(100.5) - np.log(50.5), 0, 0], atol=1e-6)
    np.testing.assert_allclose(row[:, 4], [np.log(50.5) / 10, 0, np.log(50.5) / 10], rtol=1e-6)
    np.testing.assert_array_equal(row[:, 5], [1, 0, 1])
    # ISO weeks 51, 52 and 1 (2024-12-21, 2024-12-28, 2025-01-04)
    angle = 2 * np.pi * np.array([51, 52, 1]) / 52
    np.testing.assert_allclose(row[:, 6], np.sin(angle), atol=1e-6)
    np.testing.assert_allclose(row[:, 7], np.cos(angle), atol=1e-6)
    np.testing.assert_array_equal(row[:, 8], 1)
    # climatology on every row: medians 0.2 and 0.3, mean interquartile width 0.4, known
    np.testing.assert_allclose(row[:, 9:13], [[0.2, 0.3, 0.4, 1.0]] * K, atol=1e-6)
    np.testing.assert_allclose(row[:, 13], 0.0, atol=1e-6)          # log10(1e7) − 7
    # a group left out is 0 everywhere; the target's channels are untouched
    off = context_windows(_inputs([10, 20, 40], [100, np.nan, 50]),
                          ContextChannels(other_signal=False, climatology=False))[0][0]
    np.testing.assert_array_equal(off[:, 3:6], 0)
    np.testing.assert_array_equal(off[:, 9:13], 0)
    np.testing.assert_array_equal(off[:, [0, 1, 2, 6, 7, 8]], row[:, [0, 1, 2, 6, 7, 8]])
    # weeks before a series began are masked and zero in every channel
    short, short_mask = context_windows(_inputs([np.nan, 20, 40], [np.nan] * 3),
                                        ContextChannels())
    np.testing.assert_array_equal(short_mask[0], [False, True, True])
    np.testing.assert_array_equal(short[0, 0], 0)
    np.testing.assert_array_equal(short[0, 1:, 5], 0)                 # no other signal known


def test_the_prior_standardizes_the_hand_scaled_channels_as_they_are():
    ds = synthetic_dataset(TINY_CONTEXT_FLOW)
    fixed = fixed_channels(TINY_CONTEXT_FLOW.horizon_weeks)
    np.testing.assert_array_equal(ds.stats.context_mean[fixed].numpy(), 0.0)
    np.testing.assert_array_equal(ds.stats.context_std[fixed].numpy(), 1.0)
    # the prior knows no other signal, season or climatology: their flags are 0
    assert float(ds.context[..., [5, 8]].abs().max()) == 0.0
    assert ds.context.shape[1:] == (8, TINY_CONTEXT_FLOW.channels)


def test_decoding_z_zero_keeps_the_last_week():
    """z = 0: the share of the remaining susceptibles stays the last week's, so a rate repeats
    its last week and a count falls only by its depletion (analytic inverse)."""
    rate = WeeklyHistory(pd.date_range("2025-06-07", periods=3, freq="7D"),
                         np.array([900.0, 1000.0, 1200.0]), 100_000, ED_COVID, depletes=False)
    count = WeeklyHistory(pd.date_range("2025-06-07", periods=3, freq="7D"),
                          np.array([4000.0, 5000.0, 6000.0]), 1_000_000, HOSP_COVID)
    paths = decode_weekly(np.zeros((2, 1, 2)), [rate, count])
    np.testing.assert_allclose(paths[0, 0, :, 1] * 100_000, 1200.5, rtol=1e-12)
    np.testing.assert_array_equal(paths[0, 0, :, 0], 1 - paths[0, 0, :, 1])
    n = 1_000_000
    s_before, s0 = 1 - 9000 / n, 1 - 15000 / n
    f0 = 6000.5 / (n * s_before)
    week1 = s0 * f0
    np.testing.assert_allclose(paths[1, 0, 0, 1], week1, rtol=1e-12)
    np.testing.assert_allclose(paths[1, 0, 1, 1], (s0 - week1) * f0, rtol=1e-12)


@pytest.fixture(scope="module")
def vintages(tmp_path_factory) -> dict[str, list]:
    root = tmp_path_factory.mktemp("nhsn-context")
    import_hub_time_series(NHSN, root)
    return {t: [(v.as_of, panel_of(v)) for v in cached_weekly_vintages(t, root)]
            for t in (HOSP_COVID, ED_COVID)}


def test_windows_read_only_what_was_released_by_the_vintage(vintages):
    hosp, ed = vintages[HOSP_COVID], vintages[ED_COVID]
    assert str(ed[0][0].date()) == "2025-06-18"
    sources = ContextSources(tuple(ed), tuple(ed), POPULATION)
    before = next(p for a, p in hosp if a == pd.Timestamp("2025-06-11"))
    after = next(p for a, p in hosp if a == pd.Timestamp("2025-07-02"))
    cutoff = before.last_date - pd.Timedelta(days=14)
    early = vintage_windows(before, sources, cutoff, 8, 5, ContextChannels())
    late = vintage_windows(after, sources, after.last_date - pd.Timedelta(days=14), 8, 5,
                           ContextChannels())
    assert early.context[..., 5].max() == 0 and early.context[..., 15].max() == 0
    assert late.context[..., 5].max() == 1 and late.context[..., 15].max() == 1
    # the last window of Pennsylvania: its target weeks end by the cutoff, its rows are the
    # vintage's own counts, its ED rows the share as released the same day (2025-07-02)
    pa = list(after.histories).index("42")
    rows = late.context[late.place == pa][-1]
    weeks = after.dates
    origin = int(np.searchsorted(weeks, after.last_date - pd.Timedelta(days=14),
                                 side="right")) - 1 - 5
    cases = after.histories["42"].cases[origin - 7:origin + 1]
    np.testing.assert_allclose(rows[:, 0], np.log(cases + 0.5) - np.log(cases[-1] + 0.5),
                               rtol=1e-5, atol=1e-6)
    ed_known = next(p for a, p in reversed(ed) if a <= after.as_of)
    assert ed_known.as_of == after.as_of == pd.Timestamp("2025-07-02")
    share = ed_known.histories["42"]
    week = int(np.flatnonzero(share.dates == weeks[origin])[0])
    np.testing.assert_allclose(rows[-1, 4], np.log(share.cases[week] + 0.5) / 10, rtol=1e-5)
    # a refit on 2025-07-05's data reads that vintage's windows, not a later one's
    date = pd.Timestamp("2025-07-05")
    refit = refit_windows([TrainingPool(hosp, sources)], date, 14, TINY_CONTEXT_FLOW,
                          ContextChannels())
    own = next(p for _, p in hosp if p.last_date == date)
    expected = vintage_windows(own, sources, date - pd.Timedelta(days=14), 8, 5,
                               ContextChannels())
    np.testing.assert_array_equal(refit.target, expected.target)


def test_the_tiny_member_forecasts_real_rounds_from_its_refits(vintages, tmp_path,
                                                               monkeypatch):
    hosp, ed = vintages[HOSP_COVID][:36], vintages[ED_COVID]
    member = fit_context_member(TINY_CONTEXT_FLOW, TINY_CONTEXT_REFIT,
                                [TrainingPool(hosp, context_sources(HOSP_COVID, ed))],
                                tmp_path, n_samples=200)
    assert member.name == NF_CONTEXT and len(member.models) >= 5
    rounds = hub_rounds(hosp)[-3:]
    result = run_hub_rounds(rounds, vintages[HOSP_COVID][-1][1],
                            [member, HubBaseline(HubBaselineConfig(n_samples=2000))],
                            HubBacktestConfig(n_samples=50))
    q = result.forecasts[NF_CONTEXT].select(horizons=(0, 1, 2, 3)).values
    assert np.isfinite(q).all() and (np.diff(q, axis=-1) >= 0).all() and (q >= 0).all()
    # a cell's draws depend on its own seed and its origin's refit only
    rnd = rounds[-1]
    panel = rnd.panel
    cells = Cells(tuple(panel.histories[p] for p in ("42", "06")), ("42", "06"),
                  (panel, panel), (7, 7))
    both = member.sample_paths(cells)
    alone = member.sample_paths(cells.subset([1]))
    np.testing.assert_allclose(both[1], alone[0], rtol=1e-5)        # float32 batching
    assert member.model_for(rnd.origin) is member.models[max(member.models)]
    # the same member again from the store: the same refits, the same forecast
    again = fit_context_member(TINY_CONTEXT_FLOW, TINY_CONTEXT_REFIT,
                               [TrainingPool(hosp, context_sources(HOSP_COVID, ed))],
                               tmp_path, n_samples=200)
    np.testing.assert_array_equal(again.sample_paths(cells), both)
    # paths: S never rises, counts below the people left
    s = both[..., 0]
    assert (np.diff(s, axis=-1) <= 0).all() and (both[..., 1] > 0).all()
    # two seeds: seed 0's flows are the one-seed member's (the store's keys are unchanged) and
    # draw j comes from seed j mod 2, the same noise as the single seed's draw j
    pools = [TrainingPool(hosp, context_sources(HOSP_COVID, ed))]
    two = fit_context_member(TINY_CONTEXT_FLOW, TINY_CONTEXT_REFIT, pools, tmp_path,
                             n_samples=200, n_seeds=2)
    seed1 = fit_context_member(dataclasses.replace(TINY_CONTEXT_FLOW, seed=1),
                               dataclasses.replace(TINY_CONTEXT_REFIT, seed=1), pools,
                               tmp_path, n_samples=200)
    assert two.n_seeds == 2 and set(two.models) == set(member.models)
    mixed = two.sample_paths(cells)
    np.testing.assert_allclose(mixed[:, 0::2], both[:, 0::2], rtol=1e-5)
    np.testing.assert_allclose(mixed[:, 1::2], seed1.sample_paths(cells)[:, 1::2], rtol=1e-5)
    assert not np.allclose(mixed[:, 1::2], both[:, 1::2], rtol=1e-3)     # another flow
    # a refit that diverges (in any seed) is left out, recorded, and its origins forecast by the
    # refit before it, as nf-real's: the member stays in the round
    dates = sorted(member.models)
    stored = context_module.stored_refit

    def diverging(job, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        if job.date == dates[1] and job.identity["base"] != "never":
            raise TrainingDivergedError("injected: validation NLL 30.64 at iteration 240")
        return stored(job, *args, **kwargs)

    monkeypatch.setattr(context_module, "stored_refit", diverging)
    fallen = fit_context_member(TINY_CONTEXT_FLOW, TINY_CONTEXT_REFIT, pools, tmp_path,
                                n_samples=200, n_seeds=2)
    assert set(fallen.models) == set(two.models) - {dates[1]}
    assert fallen.fallbacks == {dates[1]: "injected: validation NLL 30.64 at iteration 240; "
                                          f"forecasts from the refit of {dates[0].date()} instead"}
    assert fallen.refit_for(dates[1] + pd.Timedelta(days=7)) == dates[0]


def test_each_target_reads_the_other_signal(vintages):
    """Admissions read the ED share (the climatology) by default; the share reads admissions
    only when given them."""
    ed, hosp = vintages[ED_COVID], vintages[HOSP_COVID]
    assert dataclasses.asdict(HubMembersConfig().context)["encoder"] == "mlp"
    assert context_sources(HOSP_COVID, ed).other == tuple(ed)
    assert context_sources(ED_COVID, ed).other == ()
    assert context_sources(ED_COVID, ed, hosp).other == tuple(hosp)


def test_the_season_is_read_for_influenza_and_not_for_covid():
    """COVID-19's flow leaves the calendar out (its waves do not keep to it: the three-seed
    ablations), influenza's reads it: the season's channels 6-8 are 0 for the one and the ISO
    week's sine, cosine and 1 for the other; every other channel is the same."""
    config = HubMembersConfig()
    inputs = _inputs([10, 20, 40], [100, np.nan, 50])
    covid = context_windows(inputs, context_channels(config, own_seasons=False))[0][0]
    influenza = context_windows(inputs, context_channels(config, own_seasons=True))[0][0]
    np.testing.assert_array_equal(covid[:, 6:9], 0)
    angle = 2 * np.pi * np.array([51, 52, 1]) / 52
    np.testing.assert_allclose(influenza[:, 6:9], np.c_[np.sin(angle), np.cos(angle),
                                                        np.ones(3)], atol=1e-6)
    rest = [0, 1, 2, 3, 4, 5, *range(9, covid.shape[1])]
    np.testing.assert_array_equal(covid[:, rest], influenza[:, rest])


def test_the_flow_reads_the_seasonal_members_climatology(vintages):
    """COVID-19's admissions: the ED share is both the other signal and the climatology;
    influenza's (no ED vintage): the admissions' own earlier seasons, as each vintage released
    them, and no other signal."""
    from pipeline.members.published import context_pool

    hosp, ed = vintages[HOSP_COVID], vintages[ED_COVID]
    covid = context_pool(HOSP_COVID, hosp, ed, None, own_seasons=False)
    assert covid.sources.climatology == tuple(ed) and covid.sources.other == tuple(ed)
    own = context_pool(HOSP_COVID, hosp, (), None, own_seasons=True)
    assert own.sources.climatology == tuple(hosp) and own.sources.other == ()
    # the climatology a cell reads is its own vintage's earlier seasons: admissions (weeks from
    # 2024-11) have none at 2025-09; the ED share's own (weeks from 2022-10) have three
    last = hosp[-1][1]
    assert not np.isfinite(own.sources.climatology_at(last.as_of, [last.last_date], 5)).any()
    share = context_pool(ED_COVID, ed, (), None, own_seasons=True).sources
    assert np.isfinite(share.climatology_at(ed[-1][0], [ed[-1][1].last_date], 5)).all()
