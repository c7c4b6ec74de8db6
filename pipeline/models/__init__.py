"""Conditional density estimators: context encoders, flow backends, the combined estimator.

Entry points: ``EstimatorConfig`` / ``make_estimator_config`` + ``build_estimator(config, stats,
seed)`` -> ``ConditionalEstimator``; ``FlowConfig`` + ``build_flow``; ``EncoderConfig`` +
``build_encoder``. See docs/models.md.
"""
from pipeline.models.encoders import (EncoderConfig, MambaEncoderConfig, MLPEncoderConfig,
                                      TransformerEncoderConfig, build_encoder)
from pipeline.models.estimator import (ConditionalEstimator, EstimatorConfig, add_context_noise,
                                       build_estimator, make_estimator_config)
from pipeline.models.maf import ConditionalFlow, FlowConfig, FlowTrajectory, build_flow

__all__ = ["ConditionalEstimator", "ConditionalFlow", "EncoderConfig", "EstimatorConfig",
           "FlowConfig", "FlowTrajectory", "MLPEncoderConfig", "MambaEncoderConfig",
           "TransformerEncoderConfig", "add_context_noise", "build_encoder", "build_estimator",
           "build_flow", "make_estimator_config"]
