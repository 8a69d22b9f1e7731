"""Every public map of rotlearn.geometry names a wrong trailing shape at once ("q: expected a
tensor of shape (..., 4), got (3,)"), instead of an unpacking, broadcasting or cross-product
error from inside it; any batch shape, an empty one included, passes."""

from __future__ import annotations

import pytest
import torch

from rotlearn import geometry

# function -> the trailing shape of each of its tensor arguments, in order
TRAILING = {
    "a_from_quat": [(4,)],
    "a_from_vec": [(10,)],
    "angle": [(3, 3), (3, 3)],
    "angle_deg": [(3, 3), (3, 3)],
    "chordal_distance": [(3, 3), (3, 3)],
    "chordal_distance_sq": [(3, 3), (3, 3)],
    "hat": [(3,)],
    "quat_canonical": [(4,)],
    "quat_chordal_distance": [(4,), (4,)],
    "quat_inverse": [(4,)],
    "quat_multiply": [(4,), (4,)],
    "quat_normalize": [(4,)],
    "quat_to_rotmat": [(4,)],
    "relative_rotation": [(3, 3), (3, 3)],
    "rotmat_to_quat": [(3, 3)],
    "sixd_to_rotmat": [(6,)],
    "so3_exp": [(3,)],
    "so3_exp_quat": [(3,)],
    "so3_log": [(3, 3)],
    "so3_log_quat": [(4,)],
    "special_orthogonalize": [(3, 3)],
    "sym4_eigh_min": [(4, 4)],
    "symmatrixvec_to_quat": [(10,)],
    "validate_sym4": [(4, 4)],
    "vec_from_a": [(4, 4)],
    "vee": [(3, 3)],
}
SAMPLERS = {
    "random_quat",
    "random_rotmat",
    "random_rotmat_uniform_angle",
    "random_rotvec_uniform_angle",
    "random_unit_vectors",
}  # fmt: skip  (take sizes)


def _good(trailing: tuple[int, ...], batch: tuple[int, ...]) -> torch.Tensor:
    if trailing == (4, 4):  # symmetric, as the eigensolver and its check ask
        A = torch.randn(*batch, 4, 4, dtype=torch.float64)
        return A + A.transpose(-1, -2)
    return torch.randn(*batch, *trailing, dtype=torch.float64)


def test_every_public_map_is_listed():
    assert set(TRAILING) | SAMPLERS == set(geometry.__all__)


@pytest.mark.parametrize("name", sorted(TRAILING))
def test_a_wrong_trailing_shape_is_named(name):
    function, shapes = getattr(geometry, name), TRAILING[name]
    for batch in ((), (0,), (2, 3)):
        function(*(_good(s, batch) for s in shapes))  # any batch shape passes
    for position, trailing in enumerate(shapes):
        for wrong in ((*trailing[:-1], trailing[-1] - 1), trailing[1:] or (trailing[0] + 1,)):
            args = [_good(s, (2,)) for s in shapes]
            args[position] = torch.randn(2, *wrong, dtype=torch.float64)
            expected = ", ".join(["...", *map(str, trailing)])
            with pytest.raises(ValueError, match=rf"expected a tensor of shape \({expected}\)"):
                function(*args)


@pytest.mark.parametrize("name", sorted(n for n, shapes in TRAILING.items() if len(shapes) == 2))
def test_a_map_of_two_tensors_promotes_float32_with_float64(name):
    """As torch's elementwise ops do: float32 with float64 gives the float64 result of the same
    (float32-rounded) values, whichever argument is the float32 one (a matmul would refuse)."""
    function, shapes = getattr(geometry, name), TRAILING[name]
    wide = [_good(s, (5,)).float().double() for s in shapes]
    for narrow in range(2):
        args = [a.float() if i == narrow else a for i, a in enumerate(wide)]
        got = function(*args)
        assert got.dtype == torch.float64
        torch.testing.assert_close(got, function(*wide), rtol=0, atol=0)
