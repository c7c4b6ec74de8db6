"""The weekly forecast's one model of the epidemic: the multi-wave prior seen through the S/I/R
conversion, the joint (S, I, R, β) flows trained on it, its renewal dynamics as a particle
filter, and the NF-seeded SMC forecast member. Known answers: the conversion's closed form, the
prior's own simulator, scipy's negative binomial, a synthetic series with known β and I."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
import torch
from scipy import stats

from pipeline.members.smc import NFSeededSMCMember, batched_smc_forecasts
from pipeline.panels.history import EpiHistory
from pipeline.panels.panel import Cells
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
from tests.forecasting_helpers import forecast_one
from pipeline.inference.estimate import ObservationWindow, batch_window_context, sample_conditional
from pipeline.inference.smc import SMCConfig, seeded_filter
from pipeline.inference.smc_models import (WaveRenewalModel, negative_binomial_log_prob,
                                           reporting_pattern)
from pipeline.models.context_transforms import INFECTIOUS_FLOOR, apply_context_transform
from pipeline.models.estimator import build_estimator
from pipeline.systems.waves import WavePrior, observed_sir, recovery_rate, simulate_waves, sir_view
from pipeline.training.datasets import train_validation_split, windows_from_waves
from pipeline.training.presets import get_preset
from pipeline.training.trainer import train

SHORT = WavePrior(days=120)


def test_observed_sir_is_the_conversion_of_the_reported_cases():
    cases = np.array([[3, 0, 5, 1, 2, 4, 6, 7, 1, 0, 2]])
    sir = observed_sir(cases, population=100, window_days=7, removed_before=0.2)[0]
    assert sir.shape == (5, 3)
    np.testing.assert_allclose(sir[:, 1], np.array([21, 25, 26, 21, 22]) / 100)
    np.testing.assert_allclose(sir[:, 2], 0.2 + np.array([0, 3, 3, 8, 9]) / 100)
    np.testing.assert_allclose(sir.sum(-1), 1.0, atol=1e-15)
    assert recovery_rate(WavePrior()) == 1 / 7


def test_sir_view_reproduction_number_is_beta_s_over_gamma():
    ensemble = simulate_waves(SHORT, 20, seed=1)
    view = sir_view(ensemble, seed=2)
    rt = view.beta * view.sir[..., 0] / view.gamma
    np.testing.assert_allclose(rt, view.reproduction, rtol=1e-12)
    assert (np.diff(view.sir[..., 0], axis=1) <= 1e-15).all()     # the conversion's S never rises


def test_context_transform_reads_raw_windows_like_the_training_contexts():
    ensemble = simulate_waves(SHORT, 8, seed=0)
    ds = windows_from_waves(ensemble, window=14, seed=0)
    raw = ds.context.clone()
    raw[..., 1] = torch.exp(raw[..., 1].double()).float() - INFECTIOUS_FLOOR
    again = apply_context_transform("sir-log-infectious", raw)
    torch.testing.assert_close(again, ds.context, rtol=1e-5, atol=1e-5)
    preset = get_preset("sf-waves-joint", "mlp")
    train_ds, _ = train_validation_split(ds, preset.estimator.target_transform)
    estimator = build_estimator(preset.estimator, train_ds.stats)
    with torch.no_grad():
        direct = estimator.embed(train_ds.stats.standardize_context(ds.context, ds.mask), ds.mask)
        from_raw = estimator._embed_raw(raw, ds.mask)
    torch.testing.assert_close(from_raw, direct, rtol=1e-4, atol=1e-4)


@pytest.fixture(scope="module")
def joint_flow():
    """A small forward sf-waves-joint model trained briefly (seconds) on the prior."""
    preset = get_preset("sf-waves-joint", "mlp", n_trajectories=300)
    prior = WavePrior(days=100)
    ensemble = simulate_waves(prior, 300, seed=5)
    ds = windows_from_waves(ensemble, window=preset.dataset.window, seed=5)
    train_ds, val_ds = train_validation_split(ds, preset.estimator.target_transform)
    estimator = build_estimator(preset.estimator, train_ds.stats, seed=0)
    config = dataclasses.replace(preset.train, iterations=400, eval_every=100,
                                 early_stop_patience=None, num_threads=2)
    train(estimator, train_ds, val_ds, config)
    estimator.eval()
    return estimator, prior


def test_joint_flow_beta_interval_covers_the_known_beta(joint_flow):
    """On fresh synthetic series with known β, the forward 90 % interval of β holds the truth
    in most windows, and it is far narrower than the prior's range: β is identified."""
    estimator, prior = joint_flow
    view = sir_view(simulate_waves(prior, 40, seed=77), seed=78)
    days = np.arange(20, view.sir.shape[1], 10)
    windows, truth = [], []
    for m in range(40):
        for t in days:
            if (view.sir[m, t - 14:t, 1] > 0).all():
                windows.append(ObservationWindow(np.arange(t - 14, t, dtype=float),
                                                 view.sir[m, t - 14:t], float(t)))
                truth.append(view.beta[m, t])
    context, mask = batch_window_context(windows, "forward", 14)
    draws = sample_conditional(estimator, context, mask, 300, seed=1).double().numpy()
    low, high = np.quantile(draws[..., 3], [0.05, 0.95], axis=1)
    inside = (low <= np.array(truth)) & (np.array(truth) <= high)
    width = np.median(high - low) / (prior.beta_range[1] - prior.beta_range[0])
    assert inside.mean() >= 0.75, inside.mean()
    assert width < 0.7, width          # 400 iterations; the product's model: bench/rollouts_sf


def test_negative_binomial_matches_scipy():
    count = torch.tensor([0.0, 3.0, 17.0, 250.0], dtype=torch.float64)
    mean = torch.tensor([2.0, 5.0, 20.0, 200.0], dtype=torch.float64)
    k = torch.tensor([1.5, 10.0, 40.0, 7.0], dtype=torch.float64)
    ours = negative_binomial_log_prob(count, mean, k).numpy()
    p = (k / (k + mean)).numpy()
    np.testing.assert_allclose(ours, stats.nbinom.logpmf(count.numpy(), k.numpy(), p),
                               rtol=1e-10)


def _particles_at(view_sir: np.ndarray, infections: np.ndarray, log_beta: float,
                  prior: WavePrior, n: int, spread: float, generator: torch.Generator
                  ) -> torch.Tensor:
    """(1, n, D) particles around a known state: β and the week's infections jittered."""
    beta = torch.exp(log_beta + spread * torch.randn((1, n), generator=generator,
                                                     dtype=torch.float64))
    lags = torch.as_tensor(infections, dtype=torch.float64).expand(1, n, -1)
    scale = torch.exp(spread * torch.randn((1, n, 1), generator=generator, dtype=torch.float64))
    lags = lags * scale
    infectious = lags.sum(-1)
    s = torch.full((1, n), float(view_sir[0]), dtype=torch.float64)
    static = torch.tensor([np.log(1.0 / 7), 0.02, 0.02, 1e-6], dtype=torch.float64)
    return torch.cat([s[..., None], infectious[..., None], (1 - s - infectious)[..., None],
                      beta[..., None], lags, static.expand(1, n, 4),
                      torch.zeros((1, n, 1), dtype=torch.float64)], dim=-1)


def test_renewal_model_step_is_the_priors_step():
    """With no noise, one filter step makes the prior's new infections: S(1 − e^(−βI − ι))."""
    model = WaveRenewalModel(population=torch.tensor([[1e6]]), dispersion=torch.tensor([[50.0]]),
                             jump_rate=0.0, proposal_jump_rate=0.0)
    lags = np.array([1e-4, 2e-4, 3e-4, 2e-4, 1e-4, 3e-4, 2e-4])
    x = torch.tensor([[[0.9, lags.sum(), 0.1 - lags.sum(), 0.2, *lags, np.log(0.2), 0.0, 0.0,
                        1e-6, 0.0]]], dtype=torch.float64)
    out = model.transition(x, 0.0, 1.0, torch.Generator().manual_seed(0))[0, 0].numpy()
    new = 0.9 * -np.expm1(-(0.2 * lags.sum() + 1e-6))
    assert out[4 + 6] == pytest.approx(new, rel=1e-12)
    assert out[1] == pytest.approx(lags[1:].sum() + new, rel=1e-12)
    assert out[0] == pytest.approx(0.9 - new, rel=1e-12)
    assert out[:3].sum() == pytest.approx(1.0, abs=1e-15)


def test_renewal_filter_follows_a_synthetic_series_with_a_healthy_ess():
    """A trajectory of the prior, filtered from particles near its day-0 state: ESS stays above
    20 % of the particles on every day and the 90 % band of I holds the true I on most days."""
    prior = WavePrior(days=130)
    ensemble = simulate_waves(prior, 1, seed=11)
    view = sir_view(ensemble, seed=0)
    start, days = 20, 56
    generator = torch.Generator().manual_seed(3)
    x0 = _particles_at(view.sir[0, start], ensemble.infections[0, start:start + 7],
                       float(ensemble.log_beta[0, start + 7]), prior, 1000, 0.1, generator)
    cases = ensemble.cases[0].astype(np.float64)
    window_sums = np.convolve(cases, np.ones(7), mode="valid")          # day 6 on
    obs = torch.as_tensor(window_sums[start + 1: start + 1 + days])[None, :, None]
    _, k = reporting_pattern(torch.as_tensor(cases)[None])
    model = WaveRenewalModel(population=torch.tensor([[float(prior.population)]]),
                             dispersion=k[:, None], jump_rate=prior.jump_rate_per_day,
                             jump_sd=prior.jump_sd)
    result = seeded_filter(x0, obs, model, SMCConfig(num_particles=1000, seed=4,
                                                     quantiles=(0.05, 0.95)))
    ess = result.ess[0].numpy()
    assert ess.min() >= 200, ess.min()
    truth = window_sums[start + 1: start + 1 + days] / prior.population
    low, high = result.quantiles[0, :, 0, 1].numpy(), result.quantiles[0, :, 1, 1].numpy()
    assert np.mean((truth >= low) & (truth <= high)) >= 0.8


def _history(days: int = 140, seed: int = 0) -> EpiHistory:
    ensemble = simulate_waves(WavePrior(days=days + 40), 1, seed=seed)
    cases = ensemble.cases[0, -days:]
    sir = observed_sir(ensemble.cases[0], WavePrior().population, 7, 0.01)[-days:]
    dates = pd.date_range("2021-01-02", periods=days, freq="D")
    return EpiHistory(dates, cases, sir[:, 0], sir[:, 1], sir[:, 2], WavePrior().population)


def test_smc_member_quantiles_are_valid_and_see_only_the_past():
    preset = get_preset("sf-waves-joint", "mlp")
    ensemble = simulate_waves(SHORT, 8, seed=0)
    ds = windows_from_waves(ensemble, window=14, seed=0)
    train_ds, _ = train_validation_split(ds, preset.estimator.target_transform)
    estimator = build_estimator(preset.estimator, train_ds.stats, seed=1).eval()
    member = NFSeededSMCMember(estimator, 14, n_particles=200, filter_days=28, seed=3)
    history = _history()
    levels = np.asarray(HUB_QUANTILE_LEVELS)
    origin = history.dates[100]
    forecast = forecast_one(member, history.up_to(origin), levels=levels)
    for target in ("cases", "I"):
        q = forecast.values[target]
        assert q.shape == (4, 23) and np.isfinite(q).all() and (np.diff(q, axis=1) >= 0).all()
    np.testing.assert_allclose(forecast.values["I"], forecast.values["cases"] / history.population)
    # data after the origin cannot change the forecast
    altered = dataclasses.replace(history, cases=np.where(np.arange(len(history)) > 100,
                                                          history.cases * 5, history.cases))
    again = forecast_one(member, altered.up_to(origin), levels=levels)
    np.testing.assert_array_equal(again.values["cases"], forecast.values["cases"])
    # one batch over several origins = the same forecasts from each origin's past
    origins = [history.dates[i] for i in (90, 100)]
    batched = batched_smc_forecasts(member, altered, "place", origins, (1, 2, 3, 4), levels)
    assert set(batched.forecasts) == {("place", o) for o in origins}
    served = batched.forecast(Cells.of([history.up_to(o) for o in origins], [0, 0],
                                       ["place", "place"]), (1, 2, 3, 4), levels).count
    assert served.shape == (2, 4, 23) and np.isfinite(served).all()
    # an origin it made no forecast for has none (NaN), not an error
    missing = batched.forecast(Cells.of([history.up_to(history.dates[60])], [0], ["place"]),
                               (1, 2, 3, 4), levels).count
    assert np.isnan(missing).all()
