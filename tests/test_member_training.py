"""The forecast's members trained in a background process (pipeline.forecast.member_training):
the same models, bit for bit, as the steps would train themselves; a failure is reported and
costs nothing; a run that ends early stops it."""
from __future__ import annotations

import pytest
import torch

from pipeline import forecast as fc
from pipeline.members.nf.growth import NFGrowthMember
from pipeline.members.published import ChosenMembers, build_members
from pipeline.panels.panel import Panel
from pipeline.forecast.member_training import member_training, start_member_training
from pipeline.training.model_store import ModelStore
from tests.forecasting_helpers import random_walk_history

# each of the first tests starts a Python process that imports torch and trains the tiny models
pytestmark = pytest.mark.slow

CONFIG = fc.FORECAST_PRESETS["tiny"]
PLACE = "San Francisco"


def _flow_weights(chosen: ChosenMembers) -> dict[str, torch.Tensor]:
    flow = next(m for m in chosen.members if isinstance(m, NFGrowthMember))
    return flow.estimator.state_dict()


def test_the_background_process_stores_the_models_the_step_would_train(tmp_path):
    history = random_walk_history(60, seed=1)
    background, here = tmp_path / "background", tmp_path / "here"
    outcome = start_member_training(CONFIG, history, background).wait()
    assert outcome.ok, outcome.error
    assert outcome.seconds > 0
    record = CONFIG.track_record_config()
    panel, origins = Panel({PLACE: history}), record.origins(history)
    found = build_members(record.members, background, panel, origins)
    assert found.reused                     # the step trains nothing
    trained = build_members(record.members, here, panel, origins)
    assert not trained.reused and trained.model_key == found.model_key
    ours, theirs = _flow_weights(trained), _flow_weights(found)
    assert ours.keys() == theirs.keys()
    assert all(torch.equal(ours[k], theirs[k]) for k in ours)


def test_a_failed_background_training_is_reported_not_raised(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    outcome = start_member_training(CONFIG, random_walk_history(60, seed=1),
                                    blocker / "models").wait()
    assert not outcome.ok
    assert outcome.error.startswith("exit 1: ")
    assert "NotADirectoryError" in outcome.error or "FileExistsError" in outcome.error


def test_leaving_early_stops_the_background_process_and_leaves_no_partial_entry(tmp_path):
    root = tmp_path / "models"
    with member_training(CONFIG, random_walk_history(60, seed=1), root,
                         needed=True) as training:
        process = training.process
        assert process is not None and process.poll() is None
    assert process.poll() is not None       # stopped on leaving
    store = ModelStore(root)
    for entry in (root.iterdir() if root.is_dir() else ()):
        if entry.is_dir() and not entry.name.startswith("."):
            assert store.get(entry.name) is not None, f"{entry} is a partial entry"


def test_nothing_to_train_starts_nothing(tmp_path):
    with member_training(CONFIG, random_walk_history(60, seed=1), tmp_path,
                         needed=False) as training:
        assert not training.running
        assert training.wait().ok
