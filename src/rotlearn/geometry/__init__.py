"""Floor 1, pure math: quaternions (x, y, z, w), SO(3) maps, distances, sampling, the symmetric
4x4 eigensolver of the A representation, and the one-call maps of the representation heads
(`symmatrixvec_to_quat`, `sixd_to_rotmat`, `special_orthogonalize`). Torch only."""

from rotlearn.geometry.distance import (
    angle,
    angle_deg,
    chordal_distance,
    chordal_distance_sq,
    quat_chordal_distance,
)
from rotlearn.geometry.eigen4 import sym4_eigh_min, validate_sym4
from rotlearn.geometry.orthogonalize import special_orthogonalize
from rotlearn.geometry.quaternion import (
    quat_canonical,
    quat_inverse,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
)
from rotlearn.geometry.sampling import (
    random_quat,
    random_rotmat,
    random_rotmat_uniform_angle,
    random_rotvec_uniform_angle,
    random_unit_vectors,
)
from rotlearn.geometry.sixd import sixd_to_rotmat
from rotlearn.geometry.so3 import (
    hat,
    relative_rotation,
    so3_exp,
    so3_exp_quat,
    so3_log,
    so3_log_quat,
    vee,
)
from rotlearn.geometry.symmetric import a_from_quat, a_from_vec, symmatrixvec_to_quat, vec_from_a

__all__ = [
    "a_from_quat",
    "a_from_vec",
    "angle",
    "angle_deg",
    "chordal_distance",
    "chordal_distance_sq",
    "hat",
    "quat_canonical",
    "quat_chordal_distance",
    "quat_inverse",
    "quat_multiply",
    "quat_normalize",
    "quat_to_rotmat",
    "random_quat",
    "random_rotmat",
    "random_rotmat_uniform_angle",
    "random_rotvec_uniform_angle",
    "random_unit_vectors",
    "relative_rotation",
    "rotmat_to_quat",
    "sixd_to_rotmat",
    "so3_exp",
    "so3_exp_quat",
    "so3_log",
    "so3_log_quat",
    "special_orthogonalize",
    "sym4_eigh_min",
    "symmatrixvec_to_quat",
    "validate_sym4",
    "vec_from_a",
    "vee",
]
