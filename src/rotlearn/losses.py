"""Rotation losses (paper eqs. 17-19). Each takes (prediction, batch) and returns a scalar mean."""

from __future__ import annotations

from torch import Tensor, nn

from rotlearn.bingham import nll
from rotlearn.errors import ConfigValueError
from rotlearn.geometry import angle, chordal_distance_sq, rotmat_to_quat
from rotlearn.heads import HEADS, RotationPrediction
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


def _guess_rep(prediction: RotationPrediction) -> str:
    size = prediction.raw.shape[-1]
    names = [name for name, cls in sorted(HEADS.items()) if cls.out_dim == size]
    return names[0] if len(names) == 1 else f"<head with out_dim {size}>"


@config_target
class BinghamNLLLoss(nn.Module):
    """Mean Bingham negative log-likelihood `nll(prediction.A, batch["q"])` (paper eq. 19).

    The targets are batch["q"] (..., 4), or the quaternions of batch["R"] where the batch has no
    "q" (the sign does not matter: the likelihood is antipodally symmetric).

    Args:
        rep: the representation's name (the config's `rep.name`), optional. If given and that
            head defines no belief, construction fails with a ConfigValueError on key "rep".
    """

    def __init__(self, rep: str | None = None) -> None:
        super().__init__()
        if rep is not None and rep in HEADS and not HEADS[rep].defines_belief:
            raise ConfigValueError("rep", self._message(rep))
        self.rep = rep

    @staticmethod
    def _message(rep: str) -> str:
        return f"loss=bingham needs a head that defines a belief (rep=a); rep={rep} does not"

    def forward(self, prediction: RotationPrediction, batch: dict[str, Tensor]) -> Tensor:
        if prediction.A is None:
            raise ValueError(self._message(self.rep or _guess_rep(prediction)))
        q = batch["q"] if "q" in batch else rotmat_to_quat(batch["R"])
        return nll(prediction.A, q).mean()

    def extra_repr(self) -> str:
        return "" if self.rep is None else f"rep={self.rep!r}"
