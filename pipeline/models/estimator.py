"""ConditionalEstimator = standardization + context encoder + conditional flow.

Two unit systems:
- *original units* (what users and the estimation code see): ``log_prob``, ``sample``,
  ``noise_to_data`` take raw context windows and raw targets and return raw values/densities.
  ``log_prob`` includes the Jacobian of the target map y -> u = T(y) -> z = (u - mean) / std:
  log p(y) = log p(z) - sum_d log std_d + log|det dT/dy|.
- *standardized units* (what training uses, the dataset tensors are standardized once):
  ``standardized_log_prob``, ``standardized_trajectory``, ``layer_outputs`` take standardized
  targets and contexts (padding rows zero).

T is ``EstimatorConfig.target_transform`` (:mod:`pipeline.models.target_transforms`): the
identity for the paper's set-ups; ``"sir-log-ratio"`` for the SF forecast's joint model, whose
flow works on u = (log(I/S), log(R/S), log beta, log gamma) (D_flow = D - 1), so its samples are
on the simplex with positive rates by construction and ``log_prob`` is a density w.r.t.
(I, R, beta, gamma) (S = 1 - I - R), -inf outside that support.

The standardization is stored as buffers (``context_mean/std``, ``target_mean/std``), so a
checkpoint's ``state_dict`` carries it; ``build_estimator(config, stats)`` followed by
``load_state_dict`` rebuilds the identical model.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from pipeline.errors import ConfigError
from pipeline.models.context_transforms import (apply_context_transform,
                                                check_context_transform)
from pipeline.models.encoders import EncoderConfig, build_encoder, check_window
from pipeline.models.maf import ConditionalFlow, FlowConfig, FlowTrajectory, build_flow
from pipeline.models.standardization import STATS_FIELDS, Standardization
from pipeline.models.target_transforms import IDENTITY, TargetTransform, get_target_transform

# A fitted Standardization, or its four tensors by name (as a checkpoint stores them).
StatsLike = Standardization | Mapping[str, Tensor]


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything needed to rebuild an estimator (stored in checkpoints as a plain dict).

    features D (target size), context_channels C (observed values, then the time channel
    ``t_obs - t_target`` and, with ``absolute_time``, ``t_obs``: the layout of
    :func:`pipeline.training.datasets.time_features`, which every context builder reads from here),
    window R (maximum rows; the MLP encoder needs exactly R), encoder, flow,
    ``target_transform`` (the coordinates the flow models the target in; module doc). The
    flow's ``features`` must equal D_flow (D, or D - 1 under ``"sir-log-ratio"``) and its
    ``context_features`` the encoder's ``embedding_features`` (``make_estimator_config`` fills
    them in). Checkpoints saved before ``target_transform`` existed load as ``"identity"``.
    """

    features: int
    context_channels: int
    window: int
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    flow: FlowConfig | None = None
    absolute_time: bool = False
    target_transform: str = IDENTITY
    # The coordinates raw windows are read in (pipeline.models.context_transforms); configs
    # saved before it existed load as "identity".
    context_transform: str = IDENTITY

    def __post_init__(self) -> None:
        for name in ("features", "context_channels", "window"):
            if getattr(self, name) < 1:
                raise ConfigError(f"EstimatorConfig.{name}={getattr(self, name)}: must be >= 1")
        check_context_transform(self.context_transform, self.context_channels)
        if self.absolute_time and self.context_channels < 3:
            raise ConfigError(f"EstimatorConfig: absolute_time needs two time channels after at "
                              f"least one observed value, context_channels="
                              f"{self.context_channels}")
        flow_features = get_target_transform(self.target_transform).flow_features(self.features)
        flow = self.flow
        if flow is None:
            flow = FlowConfig(features=flow_features,
                              context_features=self.encoder.embedding_features)
            object.__setattr__(self, "flow", flow)
        if flow.features != flow_features:
            raise ConfigError(f"EstimatorConfig.flow.features={flow.features} differs from "
                              f"the {flow_features} flow coordinates of features={self.features} "
                              f"under target_transform={self.target_transform!r}")
        if flow.context_features != self.encoder.embedding_features:
            raise ConfigError(f"EstimatorConfig.flow.context_features="
                              f"{flow.context_features} differs from "
                              f"encoder.embedding_features={self.encoder.embedding_features}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def make_estimator_config(features: int, context_channels: int, window: int,
                          encoder: EncoderConfig = EncoderConfig(), *,
                          absolute_time: bool = False, target_transform: str = IDENTITY,
                          context_transform: str = IDENTITY,
                          **flow_options: Any) -> EstimatorConfig:
    """EstimatorConfig whose FlowConfig takes D_flow and E from ``features``,
    ``target_transform`` and ``encoder``; ``flow_options`` are the other FlowConfig fields
    (layers, hidden_features, backend, ...)."""
    flow_features = get_target_transform(target_transform).flow_features(features)
    flow = FlowConfig(features=flow_features, context_features=encoder.embedding_features,
                      **flow_options)
    return EstimatorConfig(features, context_channels, window, encoder, flow, absolute_time,
                           target_transform, context_transform)


def _stats_tensors(stats: StatsLike) -> dict[str, Tensor]:
    """The four standardization tensors from a ``Standardization``, a mapping, or any object
    with those attributes."""
    getter = stats.__getitem__ if isinstance(stats, Mapping) else lambda k: getattr(stats, k)
    try:
        return {k: torch.as_tensor(getter(k)).detach().to(torch.float32).reshape(-1).clone()
                for k in STATS_FIELDS}
    except (KeyError, AttributeError) as error:
        raise ConfigError(f"standardization {type(stats).__name__} lacks {error}; it needs "
                          f"{STATS_FIELDS}") from None


class ConditionalEstimator(nn.Module):
    """Density p(target | context window) in original units (module docstring)."""

    # The standardization buffers (registered in __init__).
    context_mean: Tensor
    context_std: Tensor
    target_mean: Tensor
    target_std: Tensor

    def __init__(self, encoder: nn.Module, flow: ConditionalFlow, stats: StatsLike,
                 config: EstimatorConfig | None = None) -> None:
        super().__init__()
        self.encoder, self.flow, self.config = encoder, flow, config
        # ``transform`` is the object, ``target_transform`` its name (as on Standardization).
        self.transform: TargetTransform = get_target_transform(_transform_name(stats, config))
        tensors = _stats_tensors(stats)
        for name, value in tensors.items():
            if name.endswith("_std") and not bool((value > 0).all()):
                raise ConfigError(f"standardization {name} must be > 0, got {value.tolist()}")
            self.register_buffer(name, value)
        if self.target_mean.shape != (flow.config.features,) or self.target_std.shape != self.target_mean.shape:
            raise ConfigError(f"standardization target_mean/std have shape "
                              f"{tuple(self.target_mean.shape)}/{tuple(self.target_std.shape)}, "
                              f"the flow models D={flow.config.features}")
        if self.context_std.shape != self.context_mean.shape:
            raise ConfigError("standardization context_mean and context_std differ in shape")
        if config is not None and self.context_mean.shape != (config.context_channels,):
            raise ConfigError(f"standardization context_mean has shape "
                              f"{tuple(self.context_mean.shape)}, the config has "
                              f"C={config.context_channels} channels")

    # --- metadata used by estimation / rollouts --------------------------------------------
    @property
    def window(self) -> int | None:
        return self.config.window if self.config is not None else None

    @property
    def features(self) -> int:
        """D_flow: the flow's dimension, i.e. the size of the noise ``noise_to_data`` takes."""
        return self.flow.config.features

    @property
    def target_features(self) -> int:
        """D: the target's size in original units (what ``sample`` returns)."""
        return self.transform.target_features(self.flow.config.features)

    @property
    def target_transform(self) -> str:
        """The name of the coordinates the flow models the target in (module doc)."""
        return self.transform.name

    @property
    def absolute_time(self) -> bool:
        """Whether context rows carry the ``t_obs`` channel (see EstimatorConfig)."""
        return bool(self.config.absolute_time) if self.config is not None else False

    @property
    def stats(self) -> Standardization:
        """The standardization (the buffers' values)."""
        return Standardization(self.context_mean, self.context_std, self.target_mean,
                               self.target_std, target_transform=self.target_transform)

    @property
    def target_log_abs_det(self) -> Tensor:
        """log |det dz/du| of the affine standardization = -sum log std (constant; the
        transform's y-dependent part is ``transform.log_abs_det``)."""
        return -torch.log(self.target_std).sum()

    # --- standardization (the arithmetic is ``Standardization``'s, on the buffers) ----------
    def standardize_context(self, context: Tensor, mask: Tensor) -> Tensor:
        """Original units (..., R, C) -> standardized; rows where ``mask`` is False are 0."""
        return self.stats.standardize_context(context, mask)

    def standardize_target(self, target: Tensor) -> Tensor:
        """Original units (..., D) -> standardized flow coordinates (..., D_flow)."""
        return self.stats.standardize_target(target)

    def unstandardize_target(self, z: Tensor) -> Tensor:
        """Standardized flow coordinates (..., D_flow) -> original units (..., D)."""
        return self.stats.unstandardize_target(z)

    # --- standardized units (training) -----------------------------------------------------
    def embed(self, context: Tensor, mask: Tensor | None = None) -> Tensor:
        """Flow context (B, E) of a *standardized* window (B, R, C)."""
        mask = _full_mask(context) if mask is None else mask
        check_window(context, mask, self.context_mean.shape[0])
        return self.encoder(context, mask)

    def standardized_log_prob(self, target: Tensor, context: Tensor,
                              mask: Tensor | None = None) -> Tensor:
        """log density of the standardized target given the standardized window, (B,)."""
        return self.flow.log_prob(target, self.embed(context, mask))

    def standardized_trajectory(self, target: Tensor, context: Tensor,
                                mask: Tensor | None = None) -> tuple[FlowTrajectory, Tensor]:
        """(flow trajectory f_0..f_L, embedding) for standardized inputs (kinetic loss)."""
        embedding = self.embed(context, mask)
        return self.flow.trajectory(target, embedding), embedding

    def layer_outputs(self, target: Tensor, context: Tensor,
                      mask: Tensor | None = None) -> list[Tensor]:
        """[f_0 = target, ..., f_L] (standardized inputs), data -> base."""
        return self.flow.layer_outputs(target, self.embed(context, mask))

    # --- original units ----------------------------------------------------------------------
    @property
    def context_transform(self) -> str:
        """The coordinates raw windows are read in (``EstimatorConfig.context_transform``)."""
        return self.config.context_transform if self.config is not None else IDENTITY

    def _embed_raw(self, context: Tensor, mask: Tensor | None) -> Tensor:
        mask = _full_mask(context) if mask is None else mask
        context = apply_context_transform(self.context_transform, context)
        return self.embed(self.standardize_context(context, mask), mask)

    def log_prob(self, target: Tensor, context: Tensor, mask: Tensor | None = None) -> Tensor:
        """log p(target | context) in original units, (B,); -inf outside the transform's support
        (e.g. a negative I under ``"sir-log-ratio"``), never NaN."""
        transform = self.transform
        inside = transform.in_support(target)
        # Rows outside the support are scored at a harmless in-support stand-in (the mean in
        # flow coordinates), then set to -inf: the flow never sees log of a negative number.
        stand_in = transform.inverse(self.target_mean).to(target)
        safe = torch.where(inside[..., None], target, stand_in)
        log_prob = self.flow.log_prob(self.standardize_target(safe), self._embed_raw(context, mask))
        log_prob = log_prob + self.target_log_abs_det + transform.log_abs_det(safe).to(log_prob)
        return torch.where(inside, log_prob, torch.full_like(log_prob, -math.inf))

    def noise_to_data(self, eps: Tensor, context: Tensor, mask: Tensor | None = None) -> Tensor:
        """Standard-normal noise (B, n, D) -> targets (B, n, D) in original units."""
        return self.unstandardize_target(self.flow.noise_to_data(eps, self._embed_raw(context, mask)))

    def sample(self, num_samples: int, context: Tensor, mask: Tensor | None = None,
               generator: torch.Generator | None = None) -> Tensor:
        """(B, num_samples, D) draws in original units."""
        embedding = self._embed_raw(context, mask)
        return self.unstandardize_target(self.flow.sample(num_samples, embedding, generator))

    def forward(self, target: Tensor, context: Tensor, mask: Tensor | None = None) -> Tensor:
        return self.log_prob(target, context, mask)


def _transform_name(stats: StatsLike, config: EstimatorConfig | None) -> str:
    """The target transform of an estimator: the config's; a ``Standardization`` that records
    another one was fitted in other coordinates and is refused."""
    fitted = getattr(stats, "target_transform", None)
    wanted = config.target_transform if config is not None else (fitted or IDENTITY)
    if fitted is not None and fitted != wanted:
        raise ConfigError(f"standardization was fitted for target transform {fitted!r}, the "
                          f"estimator config asks for {wanted!r}: split the dataset with "
                          f"target_transform={wanted!r} (datasets.train_validation_split)")
    return wanted


def _full_mask(context: Tensor) -> Tensor:
    return torch.ones(context.shape[:2], dtype=torch.bool, device=context.device)


def build_estimator(config: EstimatorConfig, stats: StatsLike,
                    seed: int = 0) -> ConditionalEstimator:
    """A freshly initialised estimator; the same ``seed`` gives the same weights. The global
    RNG is used inside ``fork_rng``, so the caller's RNG state is left untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        encoder = build_encoder(config.encoder, config.context_channels, config.window)
        assert config.flow is not None  # EstimatorConfig.__post_init__ fills it in
        flow = build_flow(config.flow)
    return ConditionalEstimator(encoder, flow, stats, config)


def add_context_noise(context: Tensor, mask: Tensor, sigma: float, generator: torch.Generator,
                      *, channel_std: Tensor | None = None, time_channels: int = 1) -> Tensor:
    """The paper's context-noise augmentation (sigma = 1.0 vehicle, 0.01 SIR).

    Adds N(0, sigma^2) to the observed-value channels of the real rows; the ``time_channels``
    trailing channels (``t_obs - t_target`` and, for vehicle models, ``t_obs``) and padding rows
    stay exact. sigma is in
    the data's original units; for an already standardized context pass its ``channel_std`` and
    the noise is divided by it. Returns a new tensor.
    """
    if sigma < 0:
        raise ConfigError(f"context noise sigma={sigma}: must be >= 0")
    scale = torch.full((context.shape[-1],), float(sigma), dtype=context.dtype,
                       device=context.device)
    if channel_std is not None:
        scale = scale / channel_std.to(context)
    if not 1 <= time_channels < context.shape[-1]:
        raise ConfigError(f"context noise: time_channels={time_channels} must leave at least one "
                          f"of the {context.shape[-1]} channels observed")
    scale[-time_channels:] = 0.0
    noise = torch.randn(context.shape, generator=generator, dtype=context.dtype,
                        device=context.device)
    return context + noise * scale * mask[..., None].to(context.dtype)
