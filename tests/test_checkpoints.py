"""Checkpoints: exact round trip, metadata, and rejection of damaged or mismatched files."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from pipeline.training.checkpoints import (FORMAT_VERSION, dataclass_from_dict, load_checkpoint,
                                  save_checkpoint)
from pipeline.models.standardization import Standardization
from pipeline.errors import CheckpointError
from pipeline.models.encoders import EncoderConfig
from pipeline.models.estimator import EstimatorConfig, build_estimator, make_estimator_config

WINDOW, CHANNELS, FEATURES = 4, 4, 3



def _config(kind: str = "mamba", backend: str = "zuko") -> EstimatorConfig:
    return make_estimator_config(FEATURES, CHANNELS, WINDOW,
                                 EncoderConfig(kind=kind, embedding_features=6),
                                 layers=3, hidden_features=6, backend=backend)


def _stats() -> Standardization:
    return Standardization(context_mean=torch.tensor([0.5, 0.3, 0.2, -2.5]),
                           context_std=torch.tensor([0.3, 0.1, 0.3, 1.1]),
                           target_mean=torch.tensor([0.5, 0.1, 0.4]),
                           target_std=torch.tensor([0.3, 0.05, 0.3]))


def _batch(n: int = 16):
    g = torch.Generator().manual_seed(0)
    context = torch.rand(n, WINDOW, CHANNELS, generator=g)
    mask = torch.ones(n, WINDOW, dtype=torch.bool)
    mask[:3, 0] = False  # some shorter windows
    return torch.rand(n, FEATURES, generator=g), context, mask


@pytest.fixture
def saved(tmp_path):
    estimator = build_estimator(_config(), _stats(), seed=3)
    path = save_checkpoint(tmp_path / "model.pt", estimator, config=_config(), stats=_stats(),
                           history=[{"iteration": 100, "val_nll": -1.5}],
                           data_sha256="ab" * 32, extra={"best_val_nll": -1.5, "note": None})
    return path, estimator


@pytest.mark.parametrize("kind,backend", [("mlp", "nflows"), ("transformer", "zuko"),
                                          ("mamba", "zuko")])
def test_round_trip_gives_identical_densities_and_samples(tmp_path, kind, backend):
    config = _config(kind, backend)
    estimator = build_estimator(config, _stats(), seed=1)
    save_checkpoint(tmp_path / "m.pt", estimator, config=config, stats=_stats())
    loaded = load_checkpoint(tmp_path / "m.pt", expected_config=config)
    target, context, mask = _batch()
    estimator.eval()
    with torch.no_grad():
        assert torch.equal(estimator.log_prob(target, context, mask),
                           loaded.estimator.log_prob(target, context, mask))
        eps = torch.randn(16, 5, FEATURES, generator=torch.Generator().manual_seed(2))
        assert torch.equal(estimator.noise_to_data(eps, context, mask),
                           loaded.estimator.noise_to_data(eps, context, mask))
    assert loaded.config == config


def test_metadata_is_carried(saved):
    path, _ = saved
    meta = load_checkpoint(path).meta
    assert meta.format_version == FORMAT_VERSION
    assert meta.data_sha256 == "ab" * 32
    assert meta.history == [{"iteration": 100, "val_nll": -1.5}]
    assert meta.extra == {"best_val_nll": -1.5, "note": None}
    assert set(meta.versions) >= {"flowcast", "torch", "nflows", "zuko"}
    assert torch.__version__.startswith(meta.versions["torch"])
    payload = torch.load(path, weights_only=True)
    assert torch.equal(payload["stats"]["target_std"], _stats().target_std)


def test_config_mismatch_names_the_field(saved):
    path, _ = saved
    with pytest.raises(CheckpointError, match=r"was trained for encoder kind 'mamba', asked for "
                                              r"'transformer'"):
        load_checkpoint(path, expected_config=_config("transformer"))
    other_layers = dataclasses.replace(_config(), flow=dataclasses.replace(_config().flow,
                                                                           layers=5))
    with pytest.raises(CheckpointError, match=r"flow layers 3, asked for 5"):
        load_checkpoint(path, expected_config=other_layers)


def test_truncated_file_is_rejected(saved):
    path, _ = saved
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"model.pt is truncated or corrupt"):
        load_checkpoint(path)


def test_garbage_and_missing_files_are_rejected(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a torch file at all")
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "absent.pt")
    torch.save({"state_dict": {}}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="is not a flowcast checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")


def test_altered_weights_fail_the_hash(saved):
    path, _ = saved
    payload = torch.load(path, weights_only=True)
    name = next(iter(payload["state_dict"]))
    payload["state_dict"][name] = payload["state_dict"][name] + 1e-3
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="weights do not match the SHA-256"):
        load_checkpoint(path)


def test_other_format_version_is_rejected(saved):
    path, _ = saved
    payload = torch.load(path, weights_only=True)
    payload["format_version"] = FORMAT_VERSION + 1
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match=f"format version {FORMAT_VERSION + 1}"):
        load_checkpoint(path)


class _Payload:  # a pickled class instance: code a weights-only load must refuse to run
    pass


def test_pickled_objects_are_refused(saved):
    path, _ = saved
    payload = torch.load(path, weights_only=True)
    payload["extra"] = {"object": _Payload()}
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="weights_only=True failed"):
        load_checkpoint(path)


def test_failed_save_keeps_the_previous_file(saved, monkeypatch):
    path, estimator = saved
    before = path.read_bytes()

    def broken_save(obj, handle):
        handle.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, estimator, config=_config(), stats=_stats())
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == ["model.pt"]


def test_nested_config_rebuilds_from_plain_dict():
    config = _config("transformer", "nflows")
    assert dataclass_from_dict(EstimatorConfig, dataclasses.asdict(config)) == config
