"""Per-feature affine standardization of an estimator's context and target (one implementation:
training fits it on the training split, the estimator applies it and stores it as buffers)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.errors import DatasetError
from pipeline.models.target_transforms import TargetTransform, get_target_transform

# A feature whose training spread is below this is constant (e.g. the time channel of a
# fixed-step dataset would not be, but a fixed parameter would): it is centred, not scaled.
_MIN_STD = 1e-12
STATS_FIELDS = ("context_mean", "context_std", "target_mean", "target_std")


@dataclass(frozen=True)
class Standardization:
    """Per-feature affine standardization, z = (T(x) - mean) / std, fitted on training data.

    ``target_transform`` names T (:mod:`pipeline.models.target_transforms`; ``"identity"`` for
    the paper's set-ups): the target statistics are those of the *transformed* training targets,
    so with ``"sir-log-ratio"`` ``target_mean``/``target_std`` have D - 1 entries (the flow's
    coordinates) while ``standardize_target`` takes and ``unstandardize_target`` returns targets
    in original units.
    """

    context_mean: Tensor
    context_std: Tensor
    target_mean: Tensor
    target_std: Tensor
    target_transform: str = "identity"

    @property
    def transform(self) -> TargetTransform:
        return get_target_transform(self.target_transform)

    def standardize_context(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """``x (..., C)``; with ``mask (...)`` given, padding rows are exactly zero (whatever
        they held, NaN included)."""
        z = (x - self.context_mean.to(x)) / self.context_std.to(x)
        return z if mask is None else torch.where(mask.unsqueeze(-1).bool(), z, z.new_zeros(()))

    def standardize_target(self, y: Tensor) -> Tensor:
        u = self.transform.forward(y)
        return (u - self.target_mean.to(u)) / self.target_std.to(u)

    def unstandardize_target(self, z: Tensor) -> Tensor:
        return self.transform.inverse(z * self.target_std.to(z) + self.target_mean.to(z))

    @property
    def log_abs_det(self) -> Tensor:
        """log |det dz/du| of the affine part (= -sum log std): log p(u) = log p(z) + this. With
        the identity transform u = y; otherwise add :meth:`target_log_abs_det`'s y-dependent
        term (or call it, which includes this one)."""
        return -torch.log(self.target_std.double()).sum().to(self.target_std.dtype)

    def target_log_abs_det(self, y: Tensor) -> Tensor:
        """``(...)``: log |det dz/dy| of the whole target map at ``y (..., D)`` (original units):
        log p(y) = log p(z) + this."""
        return self.log_abs_det.to(y.dtype) + self.transform.log_abs_det(y)

    def to(self, device: torch.device | str) -> Standardization:
        return Standardization(*(getattr(self, f).to(device) for f in STATS_FIELDS),
                               target_transform=self.target_transform)

    def as_dict(self) -> dict[str, Tensor]:
        """The four tensors (the transform's name is ``target_transform``)."""
        return {f: getattr(self, f) for f in STATS_FIELDS}


def _mean_std(rows: Tensor) -> tuple[Tensor, Tensor]:
    """Column mean and population std of ``rows (M, K)``, accumulated in float64."""
    if rows.shape[0] == 0:
        raise DatasetError("cannot compute standardization: the training split has no samples")
    std, mean = torch.std_mean(rows.double(), dim=0, correction=0)
    std = torch.where(std > _MIN_STD, std, torch.ones_like(std))
    return mean.float(), std.float()


def compute_standardization(context: Tensor, mask: Tensor, target: Tensor,
                            target_transform: str = "identity") -> Standardization:
    """Statistics over the real (mask True) context rows and over the targets given, the latter
    in the coordinates of ``target_transform`` (every target must lie in its support)."""
    context_mean, context_std = _mean_std(context[mask])
    transform = get_target_transform(target_transform)
    outside = ~transform.in_support(target)
    if bool(outside.any()):
        first = target[outside][0].tolist()
        raise DatasetError(f"{int(outside.sum())} of {target.shape[0]} targets lie outside the "
                           f"support of target transform {target_transform!r} (e.g. {first}); "
                           "the SIR log-ratio needs S, I, R > 0 summing to 1 and positive rates")
    target_mean, target_std = _mean_std(transform.forward(target))
    return Standardization(context_mean, context_std, target_mean, target_std,
                           target_transform=target_transform)
