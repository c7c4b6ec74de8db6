"""Training-data digests (pipeline.training.digests): a run that reuses every stored model finds
the models' keys without cutting their windows, and loads a refit only when it forecasts with
it; the keys, weights and forecasts are those of a run that cut the windows."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.members.nf import growth as nf_member
from pipeline.members.nf import real as nf_finetune
from pipeline.members.nf.flow import SyntheticWindows, stored_flow
from pipeline.members.nf.growth import GrowthModelConfig, NFGrowthMember
from pipeline.members.nf.real import FineTuneConfig, fit_finetuned_member
from pipeline.members.nf.refit import StoredRefit
from pipeline.training.digests import DIGESTS_DIR, DataDigests
from pipeline.training.model_store import ModelStore
from tests.forecasting_helpers import forecast_one, random_walk_history

TINY_FLOW = GrowthModelConfig(n_trajectories=120, iterations=30, batch_size=256,
                              hidden_features=16, flow_layers=2, flow_hidden=16)
FINETUNE = FineTuneConfig(iterations=5, batch_size=128, min_windows=50)


def test_digests_are_computed_once_then_read_back(tmp_path):
    digests, calls = DataDigests(tmp_path), []

    def compute() -> dict[str, str]:
        calls.append(1)
        return {"data_sha256": "ab" * 32}

    first = digests.get_or_compute(("inputs", 1), compute)
    again = DataDigests(tmp_path).get_or_compute(("inputs", 1), compute)
    other = digests.get_or_compute(("inputs", 2), compute)
    assert first == again == other == {"data_sha256": "ab" * 32}
    assert len(calls) == 2                      # the second look-up of ("inputs", 1) read it
    assert len(list((tmp_path / DIGESTS_DIR).glob("*.json"))) == 2


def test_an_unreadable_digest_file_is_recomputed_and_replaced(tmp_path, caplog):
    digests = DataDigests(tmp_path)
    path = digests.path(("inputs",))
    path.parent.mkdir(parents=True)
    path.write_text("{ not json")
    assert digests.get_or_compute(("inputs",), lambda: {"x": "1"}) == {"x": "1"}
    assert "unreadable training-data digests" in caplog.text
    assert json.loads(path.read_text()) == {"digests": {"x": "1"}}


def _histories() -> list:
    return [random_walk_history(70, seed=s) for s in range(3)]


def _refits(store, dates) -> nf_finetune.FineTunedGrowthMember:
    synthetic = SyntheticWindows(TINY_FLOW, DataDigests(store))
    stored = stored_flow(TINY_FLOW, store, synthetic=synthetic)
    base = NFGrowthMember(stored.estimator, TINY_FLOW, n_samples=100)
    return fit_finetuned_member(base, synthetic, _histories(), dates, FINETUNE, store)


def test_a_rerun_on_stored_models_cuts_no_windows_and_loads_refits_when_used(tmp_path,
                                                                              monkeypatch):
    history = _histories()[0]
    dates = list(history.dates[[300, 400]].normalize())
    trained = _refits(tmp_path, dates)
    assert len(trained.models) == 2
    entries = {p.name for p in tmp_path.iterdir() if not p.name.startswith(".")}

    def no_windows(*args, **kwargs):
        raise AssertionError("windows were cut on a rerun")

    monkeypatch.setattr(nf_member.NFGrowthMember, "real_windows", no_windows)
    monkeypatch.setattr(nf_member, "growth_dataset", no_windows)
    reused = _refits(tmp_path, dates)
    assert {p.name for p in tmp_path.iterdir() if not p.name.startswith(".")} == entries
    refits = [reused.models[d] for d in dates]
    assert all(isinstance(r, StoredRefit) and "estimator" not in vars(r) for r in refits)

    origin = history.up_to(dates[1] + pd.Timedelta(days=7))
    levels = np.array([0.05, 0.5, 0.95])
    ours = forecast_one(reused, origin, (1, 2), 3, levels)
    theirs = forecast_one(trained, origin, (1, 2), 3, levels)
    np.testing.assert_array_equal(ours.values["cases"], theirs.values["cases"])
    assert "estimator" in vars(refits[1]) and "estimator" not in vars(refits[0])
    first, second = trained.models[dates[1]], refits[1]
    assert isinstance(first, StoredRefit)
    assert all(torch.equal(a, b) for a, b in zip(first.estimator.state_dict().values(),
                                                 second.estimator.state_dict().values()))


def test_the_digests_give_the_keys_of_the_cut_windows(tmp_path):
    synthetic = SyntheticWindows(TINY_FLOW, DataDigests(tmp_path))
    assert synthetic.data_sha256 == SyntheticWindows(TINY_FLOW).dataset.meta.data_sha256
    stored = stored_flow(TINY_FLOW, tmp_path, synthetic=synthetic)
    assert ModelStore(tmp_path).get(stored.key) is not None


@pytest.mark.parametrize("change", ["config", "code"])
def test_a_change_of_inputs_or_code_is_a_new_digest(tmp_path, monkeypatch, change):
    digests = DataDigests(tmp_path)
    before = digests.path(("nf-growth windows", TINY_FLOW.identity()))
    if change == "config":
        after = digests.path(("nf-growth windows",
                              GrowthModelConfig(n_trajectories=121).identity()))
    else:
        monkeypatch.setattr("pipeline.training.digests.code_fingerprint", lambda: "other code")
        after = digests.path(("nf-growth windows", TINY_FLOW.identity()))
    assert before != after
