"""fit_preset: the one train-a-preset path (flowcast train, the paper tables, the forecast)."""
from __future__ import annotations

import pytest
import torch

from pipeline.models.estimator import build_estimator
from pipeline.training.checkpoints import load_checkpoint
from pipeline.training.datasets import build_dataset, train_validation_split
from pipeline.training.fit import fit_preset
from pipeline.training.presets import get_preset
from pipeline.training.trainer import train_and_save


@pytest.fixture(scope="module")
def splits():
    data = build_dataset("sir-multi", "backward", n_trajectories=6, seed=2)
    return train_validation_split(data)


def _preset(seed: int = 7):
    preset = get_preset("sir-multi", "mlp", direction="backward", seed=seed)
    return preset.with_overrides(iterations=12, batch_size=32, num_threads=1)


def test_fit_preset_writes_a_checkpoint_with_the_common_metadata(splits, tmp_path):
    train_ds, val_ds = splits
    preset = _preset()
    result = fit_preset(preset, train_ds, val_ds, tmp_path,
                        extra={"forecast_preset": "tiny", "direction": "forward"})
    assert result.iterations_run == 12
    assert {"model.pt", "history.csv", "history.json", "loss.png"} <= {
        p.name for p in tmp_path.iterdir()}
    loaded = load_checkpoint(tmp_path / "model.pt", expected_config=preset.estimator)
    extra = loaded.meta.extra
    assert extra["preset"] == load_checkpoint(tmp_path / "model.pt").meta.extra["preset"]
    assert extra["preset"]["name"] == "sir-multi"
    assert extra["preset"]["dataset"]["direction"] == "backward"
    # The preset's direction wins over a caller's contradicting one; other extras are kept.
    assert extra["direction"] == "backward" and extra["forecast_preset"] == "tiny"
    assert extra["training_preset"] == preset.run_name == "sir-multi-backward-mlp-zuko-fast"
    assert extra["best_val_nll"] == pytest.approx(result.best_val_nll)


def test_fit_preset_is_the_hand_written_sequence_and_its_checkpoint_is_the_model(splits,
                                                                                  tmp_path):
    """Same numbers as build_estimator(seed=preset.train.seed) + train_and_save, and the
    checkpoint reproduces the trained model bit for bit."""
    train_ds, val_ds = splits
    preset = _preset(seed=3)
    fitted = fit_preset(preset, train_ds, val_ds, tmp_path / "fit")
    by_hand = build_estimator(preset.estimator, train_ds.stats, seed=preset.train.seed)
    manual = train_and_save(by_hand, train_ds, val_ds, preset.train, preset.kinetic,
                            tmp_path / "hand", estimator_config=preset.estimator,
                            extra={"preset": preset.to_dict()})
    def without_clock(history: list[dict[str, float]]) -> list[dict[str, float]]:
        return [{k: v for k, v in record.items() if k != "wall_s"} for record in history]

    assert without_clock(fitted.history_dicts()) == without_clock(manual.history_dicts())
    assert all(torch.equal(fitted.best_state[k], manual.best_state[k])
               for k in manual.best_state)
    loaded = load_checkpoint(tmp_path / "fit" / "model.pt").estimator
    context, mask = train_ds.context[:8], train_ds.mask[:8]
    eps = torch.randn(8, 5, loaded.features, generator=torch.Generator().manual_seed(0))
    assert torch.equal(loaded.noise_to_data(eps, context, mask),
                       by_hand.noise_to_data(eps, context, mask))
    assert torch.equal(loaded.log_prob(train_ds.target[:8], train_ds.context[:8], mask),
                       by_hand.log_prob(train_ds.target[:8], train_ds.context[:8], mask))
