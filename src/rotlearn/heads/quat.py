"""The unit-quaternion baseline: a normalised 4-vector (paper section VI, "quat")."""

from __future__ import annotations

from torch import Tensor

from rotlearn.geometry import quat_canonical, quat_normalize, quat_to_rotmat
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.heads.base import RotationHead, RotationPrediction, register_head


@register_head
class QuatHead(RotationHead):
    """(..., 4) network output read as (x, y, z, w) -> unit quaternion -> rotation matrix."""

    name = "quat"
    out_dim = 4

    @float32_under_autocast
    def forward(self, raw: Tensor) -> RotationPrediction:
        q = quat_canonical(quat_normalize(raw))
        return RotationPrediction(R=quat_to_rotmat(q), raw=raw, q=q)
