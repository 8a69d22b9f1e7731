"""Rotation losses (paper eqs. 17-19). Each takes (prediction, batch) and returns a scalar mean."""

from __future__ import annotations

from torch import Tensor, nn

from rotlearn.bingham import BinghamNLLLoss
from rotlearn.geometry import angle, chordal_distance_sq
from rotlearn.heads import RotationPrediction
from rotlearn.trust import config_target

__all__ = ["AngularLoss", "BinghamNLLLoss", "ChordalLoss"]


@config_target
class ChordalLoss(nn.Module):
    """Mean |R - R*|_F^2 (paper eq. 17), for every head.

    For unit quaternions it equals the chordal quaternion loss 2 d^2 (4 - d^2) of the original code.
    """

    def forward(self, prediction: RotationPrediction, batch: dict[str, Tensor]) -> Tensor:
        return chordal_distance_sq(prediction.R, batch["R"]).mean()


@config_target
class AngularLoss(nn.Module):
    """Mean squared geodesic angle |Log(R R*^T)|^2 in rad^2 (paper eq. 18)."""

    def forward(self, prediction: RotationPrediction, batch: dict[str, Tensor]) -> Tensor:
        return angle(prediction.R, batch["R"]).square().mean()
