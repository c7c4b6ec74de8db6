"""The trained-model cache: reuse on same config+data, rebuild on change, damage or retrain."""
from __future__ import annotations

import json

import time

import pytest

from pipeline.errors import CheckpointError
from pipeline.io import sha256_bytes
from pipeline.training.model_store import ENTRY_FILE, ModelStore, canonical_json, model_key

CONFIG = {"preset": "sir-joint", "recipe": "fast", "encoder": "mlp", "seed": 3, "window": (5,)}


class CountingBuilder:
    """Writes a deterministic 'checkpoint' and counts how often training actually ran."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, out_dir):
        self.calls += 1
        (out_dir / "forward.pt").write_bytes(b"forward-weights")
        (out_dir / "backward.pt").write_bytes(b"backward-weights")
        return {"final_val_nll": -2.5}


def test_key_is_canonical_and_sensitive_to_config_and_data():
    reordered = dict(reversed(list(CONFIG.items())))
    assert model_key(CONFIG, "abc") == model_key(reordered, "abc")
    assert model_key(CONFIG, "abc") != model_key(CONFIG, "abd")
    assert model_key(CONFIG, "abc") != model_key({**CONFIG, "seed": 4}, "abc")
    # tuples and lists hash alike (configs round-trip through JSON as lists)
    assert model_key(CONFIG, "abc") == model_key({**CONFIG, "window": [5]}, "abc")
    assert canonical_json({"b": 1, "a": (1, 2)}) == '{"a":[1,2],"b":1}'


def test_reuses_until_config_or_data_changes(tmp_path):
    store, build = ModelStore(tmp_path / "models"), CountingBuilder()
    first = store.get_or_build(CONFIG, "data-1", build)
    assert (first.reused, build.calls) == (False, 1)
    again = store.get_or_build(CONFIG, "data-1", build)
    assert (again.reused, build.calls) == (True, 1)
    assert again.path == first.path and again.meta["final_val_nll"] == -2.5
    assert again.meta["data_sha256"] == "data-1" and again.meta["config"]["preset"] == "sir-joint"
    assert store.get_or_build(CONFIG, "data-2", build).reused is False
    assert store.get_or_build({**CONFIG, "encoder": "transformer"}, "data-1", build).reused is False
    assert build.calls == 3
    recorded = json.loads((first.path / ENTRY_FILE).read_text())
    assert recorded["files"]["forward.pt"] == sha256_bytes(b"forward-weights")


def test_retrain_forces_a_rebuild(tmp_path):
    store, build = ModelStore(tmp_path), CountingBuilder()
    store.get_or_build(CONFIG, "d", build)
    forced = store.get_or_build(CONFIG, "d", build, retrain=True)
    assert (forced.reused, build.calls) == (False, 2)
    assert store.get_or_build(CONFIG, "d", build).reused is True


def test_damaged_entry_is_rebuilt_not_trusted(tmp_path):
    store, build = ModelStore(tmp_path), CountingBuilder()
    entry = store.get_or_build(CONFIG, "d", build)
    (entry.path / "forward.pt").write_bytes(b"bit rot")
    assert store.get(entry.key) is None
    rebuilt = store.get_or_build(CONFIG, "d", build)
    assert rebuilt.reused is False and build.calls == 2
    assert (rebuilt.path / "forward.pt").read_bytes() == b"forward-weights"


def test_failed_build_leaves_no_entry(tmp_path):
    store = ModelStore(tmp_path)

    def crashing(out_dir):
        (out_dir / "forward.pt").write_bytes(b"half")
        raise RuntimeError("training diverged")

    with pytest.raises(RuntimeError, match="diverged"):
        store.get_or_build(CONFIG, "d", crashing)
    assert [p for p in tmp_path.iterdir() if p.name != ".locks"] == []
    with pytest.raises(CheckpointError, match="no files"):
        store.get_or_build(CONFIG, "d", lambda out_dir: None)


# ------------------------------------------------------- the forecast's models come from presets


def test_forecast_models_are_the_training_presets():
    """pipeline.training.presets is the single source of the weekly models' settings: the default
    forecast is sf-waves-joint × MLP × fast; tiny only shrinks; both train on the flow member's
    own multi-wave prior (one model of the epidemic), with γ fixed at 1/L."""
    from pipeline.forecast import resolve_config
    from pipeline.training.presets import get_preset

    default = resolve_config("default")
    for direction in ("forward", "backward"):
        ours = default.resolved.presets[direction]
        theirs = get_preset("sf-waves-joint", "mlp", recipe="fast", direction=direction,
                            seed=ours.train.seed, dataset_seed=ours.dataset.seed)
        assert ours == theirs and ours.dataset.direction == direction
    assert default.resolved.window == 14
    assert default.resolved.prior is default.track_record.members.growth.prior    # the member's prior
    assert default.resolved.gamma == 1 / 7

    tiny_config = resolve_config("tiny")
    tiny = tiny_config.resolved.presets["forward"]
    mlp = get_preset("sf-waves-joint", "mlp", recipe="fast", seed=tiny.train.seed,
                     dataset_seed=tiny.dataset.seed, n_trajectories=16)
    assert tiny.estimator == mlp.estimator and tiny.dataset == mlp.dataset
    assert (tiny.train.iterations, tiny.train.batch_size, tiny.train.eval_every) == (30, 256, 10)
    assert tiny.train.lr == mlp.train.lr and tiny.train.schedule == mlp.train.schedule
    assert tiny_config.resolved.prior is tiny_config.track_record.members.growth.prior


def test_forecast_model_key_follows_encoder_recipe_and_seed():
    import dataclasses

    from pipeline.forecast import resolve_config

    base = resolve_config("tiny")

    def training(**changes: object):
        return dataclasses.replace(base, training=dataclasses.replace(base.training, **changes))

    keys = {model_key(c.training_identity(), "data") for c in (
        base, resolve_config("tiny", encoder="transformer"), resolve_config("tiny", seed=1),
        training(recipe="paper"), training(iterations=31))}
    assert len(keys) == 5
    # parameters that do not touch training (sample counts, data source) keep the key
    other = dataclasses.replace(
        base, estimates=dataclasses.replace(base.estimates, n_samples=7),
        rollouts=dataclasses.replace(base.rollouts, future_paths=50))
    assert model_key(other.training_identity(), "data") == \
        model_key(base.training_identity(), "data")


def test_forecast_config_rejects_unknown_preset_parts():
    from pipeline.errors import ConfigError
    from pipeline.forecast import ForecastConfig, resolve_config
    from pipeline.forecast.settings import TrainingSettings

    with pytest.raises(ConfigError, match="unknown encoder 'lstm'"):
        resolve_config("tiny", encoder="lstm")
    with pytest.raises(ConfigError, match="unknown recipe"):
        ForecastConfig(training=TrainingSettings(recipe="slow"))
    with pytest.raises(ConfigError, match="unknown forecast preset 'huge'"):
        resolve_config("huge")


def test_a_second_builder_of_the_same_model_waits_and_reuses_it(tmp_path):
    """One builder per key: a process (here a thread) that asks for a model another one is
    building waits for it and reuses it; the model is trained once."""
    import threading

    store = ModelStore(tmp_path)
    started, calls = threading.Event(), []

    def slow(out_dir):
        calls.append(1)
        started.set()
        time.sleep(1.0)
        (out_dir / "forward.pt").write_bytes(b"weights")

    first: list = []
    builder = threading.Thread(target=lambda: first.append(store.get_or_build(CONFIG, "d", slow)))
    builder.start()
    assert started.wait(30)
    second = ModelStore(tmp_path).get_or_build(CONFIG, "d", slow)
    builder.join()
    assert len(calls) == 1
    assert first[0].reused is False and second.reused is True
    assert (second.path / "forward.pt").read_bytes() == b"weights"


def test_stored_models_only_reuses_and_refuses_to_build(tmp_path):
    """Where only stored models may be used (a step made in a forked child), a stored model is
    reused and a missing one raises instead of being trained."""
    from pipeline.errors import ModelMissingError
    from pipeline.training.model_store import stored_models_only

    def build(out_dir):
        (out_dir / "forward.pt").write_bytes(b"weights")

    store = ModelStore(tmp_path)
    built = store.get_or_build(CONFIG, "d", build)
    with stored_models_only():
        assert store.get_or_build(CONFIG, "d", build).path == built.path
        with pytest.raises(ModelMissingError, match="not in the store"):
            store.get_or_build(CONFIG, "other-data", build)
    assert store.get_or_build(CONFIG, "other-data", build).reused is False
