"""The hub round's members trained in a background process from the other end
(pipeline.hub_round.member_training), on the ED share's first real releases
(``../shared/data/nhsn``, the tiny preset with two context seeds): the round then trains nothing
and reads back the very models it would have trained itself, bit for bit."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pandas as pd
import pytest
import torch

from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages
from pipeline.data.hub.target_import import import_hub_time_series
from pipeline.hub_round.member_training import TargetInputs, hub_member_training
from pipeline.hub_round.run import hub_members_preset
from pipeline.members.nf.context import NF_CONTEXT, ContextFlowMember
from pipeline.members.nf.real import NF_REAL, FineTunedGrowthMember
from pipeline.members.nf.refit import estimator_of
from pipeline.members.published import HubMembers, build_hub_members
from pipeline.panels.hub import ED_COVID, HOSP_COVID, panel_of
from tests.test_hub_engine import NHSN
from tests.test_warm_round import _trainings

pytestmark = pytest.mark.slow

CONFIG = dataclasses.replace(hub_members_preset("tiny"), context_seeds=2,
                             background_training=True)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> list[TargetInputs]:
    """Both targets as the round builds them: the ED share's first four releases (one refit
    date among their weeks), admissions as released in the same weeks."""
    root = tmp_path_factory.mktemp("nhsn-background")
    import_hub_time_series(NHSN, root)
    ed = [(v.as_of, panel_of(v)) for v in cached_weekly_vintages(ED_COVID, root)][:4]
    admissions = [(v.as_of, panel_of(v)) for v in cached_weekly_vintages(HOSP_COVID, root)
                  if ed[0][0] <= v.as_of <= ed[-1][0]]
    return [TargetInputs(HOSP_COVID, admissions, ed, ed), TargetInputs(ED_COVID, ed, ed, admissions)]


def _build(inputs: list[TargetInputs], store: Path) -> list[HubMembers]:
    return [build_hub_members(CONFIG, store, t.vintages, t.climatology, target=t.target,
                              other_signal=t.other_signal) for t in inputs]


def _weights(members: HubMembers) -> dict[str, torch.Tensor]:
    """Every flow's weights: the context flow's seeds at every refit, nf-real's refits."""
    out: dict[str, torch.Tensor] = {}
    for member in (*members.published, *members.references):
        if isinstance(member, ContextFlowMember):
            flows = {"base": member.base, **{str(d.date()): m for d, m in member.models.items()}}
            for when, seeds in flows.items():
                for k, flow in enumerate(seeds):
                    out |= {f"{NF_CONTEXT} {when} {k} {n}": w
                            for n, w in estimator_of(flow).state_dict().items()}
        elif isinstance(member, FineTunedGrowthMember):
            for date in member.models:
                out |= {f"{NF_REAL} {date.date()} {n}": w
                        for n, w in member.model_for(date).estimator.state_dict().items()}
    return out


def test_the_background_process_stores_the_models_the_round_would_train(inputs, tmp_path,
                                                                        monkeypatch):
    background, here = tmp_path / "background", tmp_path / "here"
    with hub_member_training(CONFIG, background, inputs, False, needed=True) as training:
        assert training.running
        outcome = training.wait()
    assert outcome.ok, outcome.error
    trainings = _trainings(monkeypatch)
    found = _build(inputs, background)
    assert all(m.reused for m in found)           # the round trains nothing
    assert trainings == {NF_CONTEXT: 0, NF_REAL: 0}
    trained = _build(inputs, here)
    assert not trained[0].reused
    for ours, theirs in zip(trained, found):
        mine, other = _weights(ours), _weights(theirs)
        assert len(mine) > 20 and mine.keys() == other.keys()
        assert [k for k in mine if not torch.equal(mine[k], other[k])] == []
    context = next(m for m in found[0].references + found[0].published
                   if isinstance(m, ContextFlowMember))
    assert context.n_seeds == 2 and len(context.models) >= 1
    assert all(isinstance(d, pd.Timestamp) for d in context.models)


def test_a_warm_round_or_a_toy_preset_starts_no_process(inputs, tmp_path):
    with hub_member_training(CONFIG, tmp_path, inputs, False, needed=False) as training:
        assert not training.running
    with hub_member_training(hub_members_preset("tiny"), tmp_path, inputs, False,
                             needed=True) as training:
        assert not training.running
        assert training.wait().ok
