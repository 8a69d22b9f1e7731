"""Rotation losses (paper eqs. 17-19) and the matrix Fisher likelihood (Mohlin et al. 2020).

Each takes (prediction, batch) and returns a scalar mean."""

from __future__ import annotations

from typing import ClassVar

from torch import Tensor, nn

from rotlearn import bingham, fisher
from rotlearn.errors import ConfigError
from rotlearn.geometry import angle, chordal_distance_sq, rotmat_to_quat
from rotlearn.heads import HEADS, RotationPrediction
from rotlearn.trust import config_target

__all__ = ["AngularLoss", "BinghamNLLLoss", "ChordalLoss", "FisherNLLLoss", "LikelihoodLoss"]


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


class LikelihoodLoss(nn.Module):
    """A negative log-likelihood loss: it reads one belief parameter of the prediction and
    refuses, at construction, a head whose predictions do not carry it.

    Args:
        rep: the representation's name (the config's `rep.name`), optional. If given and that
            head lacks the belief the loss needs, construction fails with a ConfigError on
            key "rep".
    """

    option: ClassVar[str]  # the loss's config option (loss=...)
    parameter: ClassVar[str]  # the RotationPrediction attribute the loss reads
    head_flag: ClassVar[str]  # the RotationHead class attribute that promises it
    needs: ClassVar[str]  # what the head must do, in words

    def __init__(self, rep: str | None = None) -> None:
        super().__init__()
        if rep is not None and rep in HEADS and not getattr(HEADS[rep], self.head_flag):
            raise ConfigError("rep", self._message(rep))
        self.rep = rep

    @classmethod
    def _message(cls, rep: str) -> str:
        able = " or ".join(
            f"rep={name}" for name, head in sorted(HEADS.items()) if getattr(head, cls.head_flag)
        )
        return f"loss={cls.option} needs a head that {cls.needs} ({able}); rep={rep} does not"

    def belief(self, prediction: RotationPrediction) -> Tensor:
        """The prediction's belief parameter; ValueError (naming the head) where it has none."""
        value = getattr(prediction, self.parameter)
        if value is None:
            raise ValueError(self._message(self.rep or self._guess_rep(prediction)))
        return value

    @classmethod
    def _guess_rep(cls, prediction: RotationPrediction) -> str:
        """The head that gave `prediction` (which lacks the belief), from its output size."""
        size = prediction.raw.shape[-1]
        names = [
            name
            for name, head in sorted(HEADS.items())
            if head.out_dim == size and not getattr(head, cls.head_flag)
        ]
        return names[0] if len(names) == 1 else f"<head with out_dim {size}>"

    def extra_repr(self) -> str:
        return "" if self.rep is None else f"rep={self.rep!r}"


@config_target
class BinghamNLLLoss(LikelihoodLoss):
    """Mean Bingham negative log-likelihood `nll(prediction.A, batch["q"])` (paper eq. 19).

    The targets are batch["q"] (..., 4), or the quaternions of batch["R"] where the batch has no
    "q" (the sign does not matter: the likelihood is antipodally symmetric). Heads that define a
    belief (rep=a, rep=fisher) only; `rep` as in `LikelihoodLoss`. Computed with check=False:
    no host sync per step; a belief sharper than MAX_DISPERSION is scored at that bound (the
    loss stops sharpening it; it failed the run), NaN/Inf are left to `rotlearn.lit.finite`.
    """

    option, parameter, head_flag, needs = "bingham", "A", "defines_belief", "defines a belief"

    def forward(self, prediction: RotationPrediction, batch: dict[str, Tensor]) -> Tensor:
        A = self.belief(prediction)
        q = batch["q"] if "q" in batch else rotmat_to_quat(batch["R"])
        return bingham.nll(A, q, check=False).mean()


@config_target
class FisherNLLLoss(LikelihoodLoss):
    """Mean matrix Fisher negative log-likelihood `rotlearn.fisher.nll(prediction.F, batch["R"])`
    (Mohlin et al., NeurIPS 2020), in nats w.r.t. the Haar probability measure on SO(3).

    On the Fisher head it equals `BinghamNLLLoss` (the same density, A = -K(F)), computed from
    the 3 x 3 SVD instead of the 4 x 4 eigen-decomposition. Heads that give a matrix Fisher
    parameter (rep=fisher) only; `rep` as in `LikelihoodLoss`. Unchecked, as `BinghamNLLLoss`.
    """

    option, parameter, head_flag = "fisher_nll", "F", "defines_fisher"
    needs = "gives a matrix Fisher parameter"

    def forward(self, prediction: RotationPrediction, batch: dict[str, Tensor]) -> Tensor:
        return fisher.nll(self.belief(prediction), batch["R"], check=False).mean()
