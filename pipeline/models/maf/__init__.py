"""Conditional masked autoregressive flow backends behind one interface.

``build_flow(FlowConfig(...))`` returns a ``ConditionalFlow`` of the configured backend
(``"zuko"`` by default: faster and equally accurate, see docs/models.md and bench/backends.py).
"""
from __future__ import annotations

from pipeline.errors import ConfigError
from pipeline.models.maf.base import (BACKENDS, Backend, ConditionalDiagonalGaussian,
                                        ConditionalFlow, FlowConfig, FlowTrajectory, soft_clip)

__all__ = ["BACKENDS", "Backend", "ConditionalDiagonalGaussian", "ConditionalFlow", "FlowConfig",
           "FlowTrajectory", "build_flow", "soft_clip"]


def build_flow(config: FlowConfig) -> ConditionalFlow:
    """Instantiate the backend named by ``config.backend`` (parameters from the global RNG:
    callers that need reproducibility seed it, as ``build_estimator`` does)."""
    if config.backend == "nflows":
        from pipeline.models.maf.nflows_maf import NflowsMAF
        return NflowsMAF(config)
    if config.backend == "zuko":
        from pipeline.models.maf.zuko_maf import ZukoMAF
        return ZukoMAF(config)
    raise ConfigError(f"FlowConfig.backend={config.backend!r}: must be one of {BACKENDS}")
