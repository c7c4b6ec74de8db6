"""A warm round forecasts one round: with the forecast memo and the model store of last week
carried over, next week's run of the hub's ED share (its real releases, ``../shared/data/nhsn``,
the tiny preset) forecasts only the new round's cells — nf-context, nf-real and the seasonal
member included, though a new refit date and a new release of their sources came with it — and
trains only the new refit date's models, reading the earlier refits back from the store. What
it reads back is what a cold run forecasts."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from pipeline.backtest.hub_result import HubRoundsResult
from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
from pipeline.backtest.memo import ForecastMemo
from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages
from pipeline.data.hub.target_import import import_hub_time_series
from pipeline.hub_round.run import hub_members_preset
from pipeline.members.nf.context import NF_CONTEXT
from pipeline.members.nf.real import NF_REAL
from pipeline.members.nf.refit import refit_dates
from pipeline.training.model_store import ModelStore
from pipeline.members.published import build_hub_members
from pipeline.members.seasonal import SEASONAL
from pipeline.panels.hub import ED_COVID, HOSP_COVID, hub_rounds, panel_of
from pipeline.panels.panel import Panel
from tests.hub_places import PLACES
from tests.test_hub_engine import NHSN

pytestmark = pytest.mark.slow

Vintages = list[tuple[pd.Timestamp, Panel]]
# the ED share's first four releases (2025-06-18 … 07-09; refit date 2025-06-14 among their
# weeks); the fifth, of 2025-07-16, ends on 2025-07-12: a new refit date comes with next week
LAST_WEEK, THIS_WEEK = 4, 5


@pytest.fixture(scope="module")
def vintages(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Vintages]:
    root = tmp_path_factory.mktemp("nhsn-warm")
    import_hub_time_series(NHSN, root)
    return {t: [(v.as_of, _only(panel_of(v))) for v in cached_weekly_vintages(t, root)]
            for t in (HOSP_COVID, ED_COVID)}


def _only(panel: Panel) -> Panel:
    return panel.only([p for p in PLACES if p in panel.places])


def _trainings(monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """How many models of nf-context and nf-real are trained (a pre-training or a refit): the
    builds the model store runs, by the member that asked for them (its store key's kind)."""
    calls = {NF_CONTEXT: 0, NF_REAL: 0}
    put = ModelStore.put

    def counting(store: ModelStore, key: str, build: Callable[..., Any],
                 meta: Any = None) -> Any:
        kinds = set((meta or {}).get("config", {}))
        for name in calls:
            if kinds & {name, f"{name} refit"}:
                calls[name] += 1
        return put(store, key, build, meta)

    monkeypatch.setattr(ModelStore, "put", counting)
    return calls


def _week(vintages: dict[str, Vintages], releases: int, store: Path, memos: Path
          ) -> tuple[HubRoundsResult, dict[str, tuple[int, int]]]:
    """The ED share's run of the week of its ``releases``-th release, as ``run_hub_round``
    makes it (admissions as released by then the other signal, the share its climatology),
    each member through its own memo in ``memos``: the result, and each member's memo
    (hits, misses)."""
    ed = vintages[ED_COVID][:releases]
    admissions = [v for v in vintages[HOSP_COVID] if v[0] <= ed[-1][0]]
    members = build_hub_members(hub_members_preset("tiny"), store, ed, ed, target=ED_COVID,
                                other_signal=admissions)
    memo = {m.name: ForecastMemo.load(memos / f"{m.name}.npz")
            for m in (*members.published, *members.references)}
    config = HubBacktestConfig(n_samples=50, burn_in_weeks=8)       # the tiny preset's burn-in
    result = run_hub_rounds(hub_rounds(ed), ed[-1][1],
                            [memo[m.name].wrap(m, config.n_samples) for m in members.published],
                            config, references=[memo[m.name].wrap(m, config.n_samples)
                                                for m in members.references])
    for each in memo.values():
        each.save()
    return result, {name: (each.hits, each.misses) for name, each in memo.items()}


def test_a_warm_round_forecasts_only_the_new_round_and_trains_only_the_new_refit(
        vintages: dict[str, Vintages], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    last_dates = [p.last_date for _, p in vintages[ED_COVID][:THIS_WEEK]]
    new_refits = set(refit_dates(last_dates, 4)) - set(refit_dates(last_dates[:LAST_WEEK], 4))
    assert new_refits == {pd.Timestamp("2025-07-12")}        # the week brings a refit date
    store, memos = tmp_path / "store", tmp_path / "memo"
    trainings = _trainings(monkeypatch)
    before, cold = _week(vintages, LAST_WEEK, store, memos)
    assert all(hits == 0 for hits, _ in cold.values())
    # the first week trains nf-context's prior and its refit of 2025-06-14, nf-real that refit
    assert trainings == {NF_CONTEXT: 2, NF_REAL: 1}

    trainings.update({NF_CONTEXT: 0, NF_REAL: 0})
    after, warm = _week(vintages, THIS_WEEK, store, memos)
    # one training each: the refit of 2025-07-12; the prior and the refit of 2025-06-14 are
    # read back from the store
    assert trainings == {NF_CONTEXT: 1, NF_REAL: 1}
    assert after.places == before.places
    assert len(after.rounds) == len(before.rounds) + 1
    for name in (NF_CONTEXT, NF_REAL, SEASONAL, *warm):
        # every cell of last week's rounds (and of the burn-in) read back; the new round's
        # cells, one per place, forecast
        assert warm[name] == (cold[name][1], len(after.places)), name

    # what the warm week read back is what a cold run of the same week forecasts (up to the
    # flows' float32 arithmetic: a cold run forecasts last week's cells in another batch)
    trainings.update({NF_CONTEXT: 0, NF_REAL: 0})
    again, fresh = _week(vintages, THIS_WEEK, store, tmp_path / "cold-memo")
    assert trainings == {NF_CONTEXT: 0, NF_REAL: 0}          # every model from the store
    assert all(hits == 0 for hits, _ in fresh.values())
    assert set(again.forecasts) == set(after.forecasts)
    for name, q in after.forecasts.items():
        np.testing.assert_allclose(q.values, again.forecasts[name].values, rtol=1e-5,
                                   err_msg=name)
    assert after.samples is not None and again.samples is not None
    np.testing.assert_allclose(after.samples, again.samples, rtol=1e-5)
