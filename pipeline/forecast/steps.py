"""Steps 4–8 of the weekly forecast (the epidemic model's), each a plain function of typed
inputs and outputs; step 9, the published forecast, is :mod:`pipeline.forecast.published_forecast`.

4. :func:`latest_estimates` — forward estimate of the day after the last observation and backward
   estimate of the day before the last window (both from the latest R observations).
5. :func:`rollouts` — rolling rollouts re-anchored every 7 and 28 days, forward and backward, and
   :func:`future_paths`: forward sample paths past the last observed day (the paper's rollout
   forecast; the published forecast is step 9's).
6. :func:`parameter_track` — β, γ and R_t over time (posterior quantiles per day).
7. :func:`nll_table` — the paper's Table 5: mean NLL of the observed state under the flow's state
   marginal at random days along the SF trajectory (forward / backward).
8. :func:`seeded_smc` — the paper's hybrid on the multi-wave model
   (:func:`pipeline.inference.hybrid.nf_seeded_wave_smc`).

One model of the epidemic: the joint flows are trained on the flow member's multi-wave prior seen
through the S/I/R conversion, so they estimate (S, I, R, β) with γ = 1/L fixed by the
conversion's window (appended to every draw as a constant, so R_t = β·S/γ per sample); the SMC
filters the same prior's dynamics. The context window is R = 14 days (the product's, not the
paper's five observations). Every random step draws from a generator seeded by
``ForecastConfig.seed`` plus a fixed per-step offset, so the same seed, data and model give the
same numbers.
"""
from __future__ import annotations

import functools

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from pipeline.members.nf.flow import single_thread
from pipeline.panels.history import EpiHistory
from pipeline.evaluation.metrics import kde_log_prob, mean_nll
from pipeline.forked import ChildBuild, start_in_child
from pipeline.evaluation.scoring import CENTRAL_LEVELS
from pipeline.forecast.config import ForecastConfig
from pipeline.forecast.results import (FuturePaths, LatestEstimates, Rollouts, SIRArrays,
                                       SMCRun, TrainedModels)
from pipeline.inference.estimate import (ObservationWindow, batch_window_context, estimate,
                                         sample_conditional)
from pipeline.inference.hybrid import WaveSMCConfig, nf_seeded_wave_smc
from pipeline.inference.rollout import RolloutConfig, RolloutResult, rollout, rolling_rollout
from pipeline.inference.seeded_rollout import (SeededRolloutConfig, seeded_future_rollout,
                                               seeded_rolling_rollout)
from pipeline.inference.smc import DEFAULT_QUANTILES
from pipeline.names import DIRECTIONS, JOINT_NAMES, Direction
from pipeline.training.datasets import WAVE_TARGET_FEATURES
from pipeline.progress import ProgressReporter


# Encoder choice -> the paper's Table 5 column name.
VARIANT_LABELS = {"transformer": "Transformer", "transformer-ke": "Transformer + KE",
                  "mamba": "Mamba-SSM", "mlp": "MLP"}
# The report's one interval convention: 50 % and 90 % central intervals (plus the median).
REPORT_LEVELS = CENTRAL_LEVELS
PARAMETER_LEVELS = (0.025, *REPORT_LEVELS, 0.975)


def _window_at(sir: SIRArrays, target: int, direction: Direction, r: int,
               target_time: float | None = None) -> ObservationWindow:
    """The R observations before (forward) or after (backward) day index ``target``."""
    rows = slice(target - r, target) if direction == "forward" else slice(target + 1,
                                                                          target + 1 + r)
    time = float(sir.times[target]) if target_time is None else target_time
    return ObservationWindow(times=sir.times[rows], values=sir.values[rows], target_time=time)


def _last_window(sir: SIRArrays, r: int, target_time: float) -> ObservationWindow:
    """The latest R observations, for a target time after (forward) or before (backward) them."""
    return ObservationWindow(times=sir.times[-r:], values=sir.values[-r:], target_time=target_time)


def with_fixed_gamma(draws: Tensor, gamma: float) -> Tensor:
    """(..., 4) draws of (S, I, R, β) -> (..., 5) with γ appended: the conversion's 1/L, the
    same for every draw (not estimated: :mod:`pipeline.systems.waves`)."""
    return torch.cat([draws, torch.full_like(draws[..., :1], gamma)], dim=-1)


def _draws_at(models: TrainedModels, sir: SIRArrays, targets: np.ndarray, direction: Direction,
              config: ForecastConfig, seed: int) -> Tensor:
    """(len(targets), n_samples, 5) joint draws (γ fixed) at the given day indices, one flow
    call."""
    r = config.resolved.window
    windows = [_window_at(sir, int(t), direction, r) for t in targets]
    context, mask = batch_window_context(windows, direction, r)
    draws = sample_conditional(models.by_direction(direction), context, mask,
                               config.estimates.n_samples, seed).double()
    return with_fixed_gamma(draws, config.resolved.gamma)


def latest_estimates(models: TrainedModels, sir: SIRArrays,
                     config: ForecastConfig) -> LatestEstimates:
    r = config.resolved.window
    targets: dict[Direction, float] = {"forward": float(sir.times[-1]) + 1.0,
                                       "backward": float(sir.times[-r]) - 1.0}
    rows: list[dict[str, object]] = []
    samples: dict[Direction, Tensor] = {}
    dates: dict[Direction, str] = {}
    for direction in DIRECTIONS:
        est = estimate(models.by_direction(direction),
                       _last_window(sir, r, targets[direction]), direction,
                       n_samples=config.estimates.n_samples, seed=config.step_seed("latest"),
                       names=WAVE_TARGET_FEATURES, window_length=r)
        dates[direction] = str((sir.dates[0] + pd.Timedelta(days=targets[direction])).date())
        samples[direction] = with_fixed_gamma(est.samples.double(), config.resolved.gamma)
        rows += _summary_rows(samples[direction], direction, dates[direction])
    return LatestEstimates(pd.DataFrame(rows), samples, dates)


def _summary_rows(samples: Tensor, direction: Direction, date: str) -> list[dict[str, object]]:
    q = torch.quantile(samples, torch.tensor([0.025, 0.5, 0.975], dtype=samples.dtype), dim=0)
    return [{"direction": direction, "date": date, "component": name,
             "mean": float(samples[:, d].mean()), "std": float(samples[:, d].std()),
             "q0.025": float(q[0, d]), "q0.5": float(q[1, d]), "q0.975": float(q[2, d])}
            for d, name in enumerate(JOINT_NAMES)]


def rollout_settings(config: ForecastConfig, n_paths: int, seed: int) -> RolloutConfig:
    """The rollouts' sampling: the flows predict the *observed* S/I/R (the conversion's), so a
    path feeds back its own draws as they are (no added noise); each path keeps a share of its
    flow noise from day to day (``RolloutSettings.noise_persistence``)."""
    return RolloutConfig(n_paths=n_paths, feedback_noise_sigma=0.0, seed=seed,
                         noise_persistence=config.rollouts.noise_persistence)


def rollouts(models: TrainedModels, sir: SIRArrays, config: ForecastConfig,
             progress: ProgressReporter | None = None) -> Rollouts:
    """Rolling rollouts re-anchored every W days (W in ``rollouts.windows``), fw and bw: the
    backward ones in a forked child while this process draws the forward ones
    (:mod:`pipeline.forked`), each on one torch thread, so a view's draws never depend on
    where it ran."""
    views: list[tuple[Direction, int]] = [(d, every) for d in DIRECTIONS
                                          for every in config.rollouts.windows]

    def draw(subset: list[tuple[Direction, int]],
             reporter: ProgressReporter | None) -> Rollouts:
        out: Rollouts = {}
        with single_thread():
            for direction, every in subset:
                out[(direction, every)] = rolling_view(models, sir, config, direction, every,
                                                       reporter)
        return out

    backward = start_in_child(lambda: draw([v for v in views if v[0] == "backward"], None))
    drawn = {**draw([v for v in views if v[0] != "backward"], progress), **backward.result()}
    return {view: drawn[view] for view in views}


def rolling_view(models: TrainedModels, sir: SIRArrays, config: ForecastConfig,
                 direction: Direction, every: int,
                 progress: ProgressReporter | None = None) -> RolloutResult:
    """One rolling view of the report: forward ones as ``rollouts.forward`` says (the flow's
    estimate carried on by the prior, or the chained flow), backward ones chained."""
    seed = config.step_seed("rollout") + every
    if direction == "forward" and config.rollouts.forward == "flow-seeded-prior":
        return seeded_rolling_rollout(
            models.forward, sir.times, sir.values, every, config.resolved.prior,
            SeededRolloutConfig(n_paths=config.rollouts.paths, seed=seed),
            names=WAVE_TARGET_FEATURES, window_length=config.resolved.window, progress=progress)
    return rolling_rollout(models.by_direction(direction), sir.times, sir.values, every,
                           direction, rollout_settings(config, config.rollouts.paths, seed),
                           names=WAVE_TARGET_FEATURES, window_length=config.resolved.window,
                           progress=progress)


def future_paths(models: TrainedModels, sir: SIRArrays, config: ForecastConfig) -> FuturePaths:
    """Forward sample paths for ``rollouts.forecast_days`` days after the last observed day."""
    r, days = config.resolved.window, config.rollouts.forecast_days
    seed = config.step_seed("future")
    if config.rollouts.forward == "flow-seeded-prior":
        result = seeded_future_rollout(
            models.forward, sir.times, sir.values, days, config.resolved.prior,
            SeededRolloutConfig(n_paths=config.rollouts.future_paths, seed=seed),
            names=WAVE_TARGET_FEATURES, window_length=r)
    else:
        window = _last_window(sir, r, float(sir.times[-1]) + 1.0)
        result = rollout(models.forward, window, days, 1.0, "forward",
                         rollout_settings(config, config.rollouts.future_paths, seed),
                         names=WAVE_TARGET_FEATURES, window_length=r)
    dates = pd.date_range(sir.dates[-1] + pd.Timedelta(days=1), periods=days, freq="D")
    return FuturePaths(dates, result.samples, sir.dates[-1].date())


def parameter_track(models: TrainedModels, sir: SIRArrays,
                    config: ForecastConfig) -> pd.DataFrame:
    """β, γ (and the state) per day from the R observations before (fw) / after (bw) the day.

    Long table: direction, date, component, mean, std, q0.025, q0.05, q0.25, q0.5, q0.75,
    q0.95, q0.975; one flow call per direction for all days at once. Component ``Rt`` is the
    effective reproduction number β·S/γ computed per joint sample (its posterior, not a ratio of
    medians); γ is the conversion's fixed 1/L (its rows are that constant); the report's
    intervals are the 50 % and 90 % ones. Drawn on one torch thread, so the track is the same
    whether it is drawn here or in a child (:func:`start_parameter_track`).
    """
    r, n, stride = config.resolved.window, len(sir.times), config.estimates.parameter_stride_days
    frames = []
    for direction in DIRECTIONS:
        targets = (np.arange(r, n, stride) if direction == "forward"
                   else np.arange(0, n - r, stride))
        with single_thread():
            samples = _draws_at(models, sir, targets, direction, config,
                                config.step_seed("params"))
        rt = samples[:, :, 3] * samples[:, :, 0] / samples[:, :, 4]                 # β S / γ
        samples = torch.cat([samples, rt[..., None]], dim=-1)
        q = torch.quantile(samples, torch.tensor(PARAMETER_LEVELS, dtype=torch.float64), dim=1)
        for d, name in enumerate((*JOINT_NAMES, "Rt")):
            frames.append(pd.DataFrame({
                "direction": direction, "date": sir.dates[targets].strftime("%Y-%m-%d"),
                "component": name, "mean": samples[:, :, d].mean(1).numpy(),
                "std": samples[:, :, d].std(1).numpy(),
                **{f"q{level:g}": q[k, :, d].numpy()
                   for k, level in enumerate(PARAMETER_LEVELS)}}))
    return pd.concat(frames, ignore_index=True)


def start_parameter_track(models: TrainedModels, sir: SIRArrays,
                          config: ForecastConfig) -> ChildBuild[pd.DataFrame]:
    """:func:`parameter_track` started in a forked child (:mod:`pipeline.forked`), drawn while
    this process draws the rollouts; step ``beta-gamma-estimates`` collects it."""
    return start_in_child(functools.partial(parameter_track, models, sir, config))


def nll_table(models: TrainedModels, sir: SIRArrays, config: ForecastConfig) -> pd.DataFrame:
    """Mean NLL of the observed (S, I, R) at ``nll_locations`` random days, fw and bw.

    The joint flow models (S, I, R, β, γ); the true β, γ of SF are unknown, so we score the
    *state marginal*: a Gaussian KDE (``metrics.kde_log_prob``) of the flow's (S, I, R) draws,
    evaluated at the observed state — the paper's "NLL of the estimated conditional density given
    the true state", aggregated across compartments (one joint 3-D density).
    """
    r, n = config.resolved.window, len(sir.times)
    generator = np.random.default_rng(config.step_seed("nll"))
    rows = []
    for direction in DIRECTIONS:
        candidates = np.arange(r, n) if direction == "forward" else np.arange(0, n - r)
        targets = np.sort(generator.choice(
            candidates, size=min(config.estimates.nll_locations, len(candidates)),
            replace=False))
        samples = _draws_at(models, sir, targets, direction, config, config.step_seed("nll"))
        log_p = kde_log_prob(samples[..., :3], torch.as_tensor(sir.values[targets]))
        rows.append({"direction": direction,
                     "variant": VARIANT_LABELS.get(models.encoder, models.encoder),
                     "locations": len(targets), "mean_nll": mean_nll(log_p.numpy())})
    return pd.DataFrame(rows)


def nll_table_variants(models: TrainedModels, variants: dict[str, TrainedModels],
                       sir: SIRArrays, config: ForecastConfig) -> pd.DataFrame:
    """:func:`nll_table` of the run's models and of every cached variant, same days and seed."""
    frames = [nll_table(m, sir, config) for m in (models, *variants.values())]
    return pd.concat(frames, ignore_index=True)


def seeded_smc(models: TrainedModels, history: EpiHistory, sir: SIRArrays,
               config: ForecastConfig) -> SMCRun:
    """NF-seeded SMC over the last ``smc.days`` days on the multi-wave model: draws of the
    forward joint flow at the first day seed the filter, which then follows the reported cases
    of ``history`` (the nowcast's median where days are still being reported;
    :func:`pipeline.inference.hybrid.nf_seeded_wave_smc`)."""
    r, days = config.resolved.window, config.smc.days
    start = len(sir.times) - days
    context, mask = batch_window_context([_window_at(sir, start, "forward", r)], "forward", r)
    settings = WaveSMCConfig(n_particles=config.smc.particles, seed=config.step_seed("smc"),
                             # the report's 50 %/90 % bands need these levels recorded
                             quantiles=tuple(sorted({*DEFAULT_QUANTILES, *REPORT_LEVELS})))
    run = nf_seeded_wave_smc(models.forward, context, mask,
                             torch.as_tensor(history.cases, dtype=torch.float64)[None],
                             torch.tensor([float(history.population)]), days,
                             config.resolved.prior, settings)
    return SMCRun(result=run.smc, dates=sir.dates[start:])
