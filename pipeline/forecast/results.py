"""The typed outputs of the forecast steps, and :class:`ForecastResults`, the run as a whole.

The report (:mod:`pipeline.forecast.report.weekly`), the run's files (:mod:`pipeline.forecast.publish`) and
the Prefect flow read these types and nothing else.
"""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from torch import Tensor

from pipeline.backtest.track_record import TrackRecord
from pipeline.forecast.config import ForecastConfig
from pipeline.inference.estimate import Estimator
from pipeline.inference.rollout import RolloutResult
from pipeline.inference.smc import SMCResult
from pipeline.names import JOINT_NAMES, Direction
from pipeline.systems.waves import WaveEnsemble


@dataclass(frozen=True)
class SIRArrays:
    """An S/I/R frame as arrays: ``times`` in days since the first date (T,), ``values`` (T, 3)."""

    times: np.ndarray
    values: np.ndarray
    dates: pd.DatetimeIndex


@dataclass(frozen=True, eq=False)
class TrainingData:
    """The synthetic ensemble the joint models train on (its windows are cut when a model is
    trained: ``forecast.joint_models.training_windows``) and its hash."""

    ensemble: WaveEnsemble
    seed: int
    data_sha256: str
    n_trajectories: int


@dataclass(frozen=True)
class TrainedModels:
    forward: Estimator
    backward: Estimator
    key: str
    reused: bool
    path: Path
    histories: dict[Direction, list[dict[str, float]]]
    best_val_nll: dict[Direction, float]
    encoder: str

    def by_direction(self, direction: Direction) -> Estimator:
        return self.forward if direction == "forward" else self.backward


@dataclass(frozen=True)
class LatestEstimates:
    """Summaries of the latest forward (next day) and backward (day before the window) estimates."""

    table: pd.DataFrame  # direction, date, component, mean, std, q0.025, q0.5, q0.975
    samples: dict[Direction, Tensor]  # (n, len(names)) joint draws (the report's R_t)
    dates: dict[Direction, str]
    names: tuple[str, ...] = JOINT_NAMES


@dataclass(frozen=True)
class FuturePaths:
    dates: pd.DatetimeIndex
    samples: Tensor          # (P, H, 4): S, I, R, beta (gamma is the fixed 1/L)
    reference_date: dt.date


@dataclass(frozen=True)
class SMCRun:
    """The NF-seeded filter over the last days: its result and the days it ran over."""

    result: SMCResult
    dates: pd.DatetimeIndex

    def band_frame(self, n_sigma: float = 3.0) -> pd.DataFrame:
        lower, upper = self.result.sigma_band(n_sigma)
        frames = [pd.DataFrame({
            "date": self.dates.strftime("%Y-%m-%d"), "component": name,
            "mean": self.result.mean[0, :, d].numpy(),
            f"lower_{n_sigma:g}sigma": lower[0, :, d].numpy(),
            f"upper_{n_sigma:g}sigma": upper[0, :, d].numpy()})
            for d, name in enumerate(self.result.state_names)]
        return pd.concat(frames, ignore_index=True)


Rollouts = dict[tuple[Direction, int], RolloutResult]


@dataclass(frozen=True)
class CountySkill:
    """The published method's skill across California's counties (step ``county-skill``):
    ``relative_wis[target][forecaster]``, the geometric mean over counties of relative WIS
    (``h1``…``h4``, ``all``); ``share_beating_baseline[target]`` and ``coverage[target]`` (50 %,
    90 %) of the published forecast; ``reused``: read from the kept summary."""

    vintage: str
    n_counties: int
    n_origins: int
    first_origin: str
    last_origin: str
    relative_wis: dict[str, dict[str, dict[str, float | None]]]
    share_beating_baseline: dict[str, float]
    coverage: dict[str, tuple[float, float]]
    reused: bool = False


@dataclass(frozen=True)
class ModelOutputs:
    """The epidemic model's part of a run: what the report's diagnostic sections draw."""

    config: ForecastConfig
    sir_frame: pd.DataFrame
    vintage: str
    models: TrainedModels
    parameters: pd.DataFrame
    rollouts: Rollouts
    nll: pd.DataFrame
    smc: SMCRun


@dataclass(frozen=True)
class ForecastResults:
    config: ForecastConfig
    sir_frame: pd.DataFrame     # the S/I/R the run read (days being reported: nowcast median)
    vintage: str
    stale: bool
    stale_notes: tuple[str, ...]
    models: TrainedModels
    latest: LatestEstimates
    rollouts: Rollouts
    future: FuturePaths
    parameters: pd.DataFrame
    nll: pd.DataFrame
    smc: SMCRun
    weekly: TrackRecord                  # the published forecast and its real-time backtest
    data_as_of: str | None = None           # DataSF's own "data as of" stamp, when it gave one
    # seconds per step, in the order run (the e2e benchmark reads them)
    timings: dict[str, float] = field(default_factory=dict, compare=False)
    county_skill: CountySkill | None = None  # the method's skill across California's counties

    @property
    def reference_date(self) -> str:
        return str(self.future.reference_date)

    def model_outputs(self) -> ModelOutputs:
        return ModelOutputs(config=self.config, sir_frame=self.sir_frame, vintage=self.vintage,
                            models=self.models, parameters=self.parameters,
                            rollouts=self.rollouts, nll=self.nll, smc=self.smc)
