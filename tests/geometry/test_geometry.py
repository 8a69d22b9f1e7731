"""Property tests of rotlearn.geometry: quaternions (x, y, z, w), SO(3) maps, distances, sampling.

Random inputs come from hypothesis-drawn seeds fed to a torch.Generator, so every failure is
reproducible. scipy.spatial.transform.Rotation (also scalar-last) is the independent reference.

Tolerances: float32 has eps ~1.2e-7 and these maps chain O(10) operations on O(1) numbers, so
1e-5 (~100 ulp) bounds their rounding; float64 uses 1e-12 (~5000 ulp) for the same reason.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from rotlearn.geometry import (
    angle,
    angle_deg,
    chordal_distance,
    chordal_distance_sq,
    hat,
    quat_canonical,
    quat_chordal_distance,
    quat_inverse,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    random_quat,
    random_rotmat,
    random_rotmat_uniform_angle,
    random_rotvec_uniform_angle,
    random_unit_vectors,
    rotmat_to_quat,
    so3_exp,
    so3_exp_quat,
    so3_log,
    so3_log_quat,
    vee,
)
from tests.conftest import ATOL, DTYPES, gen

PROPS = settings(max_examples=50, deadline=None)

seeds = st.integers(min_value=0, max_value=2**32 - 1)
shapes = st.sampled_from([(), (3,), (2, 3)])


# ---------------------------------------------------------------------------------------------
# helpers (independent of the code under test where it matters)
# ---------------------------------------------------------------------------------------------


def randn(seed: int, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    return torch.randn(shape, generator=gen(seed), dtype=dtype)


def unit_quats(seed: int, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """Haar-random unit quaternions of both signs (not canonicalised), built without rotlearn."""
    q = torch.randn((*shape, 4), generator=gen(seed), dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).to(dtype)


def scipy_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Reference R(q) from scipy, in float64, for (..., 4) quaternions (x, y, z, w)."""
    flat = q.detach().to(torch.float64).reshape(-1, 4).numpy()
    mats = Rotation.from_quat(flat).as_matrix().reshape(*q.shape[:-1], 3, 3)
    return torch.from_numpy(mats)


def rotmats(seed: int, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """Haar-random rotation matrices from scipy (float64 maths, then cast)."""
    return scipy_rotmat(unit_quats(seed, shape, torch.float64)).to(dtype)


def quat_of_angle_axis(theta: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternion of a rotation by theta (...) about unit axis (..., 3), in float64."""
    half = 0.5 * theta.unsqueeze(-1)
    return torch.cat((torch.sin(half) * axis, torch.cos(half)), dim=-1)


def unit_axes(seed: int, shape: tuple[int, ...]) -> torch.Tensor:
    v = torch.randn((*shape, 3), generator=gen(seed), dtype=torch.float64)
    return v / v.norm(dim=-1, keepdim=True)


def assert_rotation(R: torch.Tensor, atol: float) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=atol, rtol=0)
    torch.testing.assert_close(
        torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=atol, rtol=0
    )


def assert_same_quat(q1: torch.Tensor, q2: torch.Tensor, atol: float) -> None:
    """q1 == +-q2 elementwise over the batch."""
    d = torch.minimum((q1 - q2).norm(dim=-1), (q1 + q2).norm(dim=-1))
    assert d.max().item() <= atol, d.max().item()


# Exactly representable rotations: 0 and 180 degrees, and 180 degrees composed with 90.
EXACT_180 = [
    torch.diag(torch.tensor([1.0, -1.0, -1.0])),
    torch.diag(torch.tensor([-1.0, 1.0, -1.0])),
    torch.diag(torch.tensor([-1.0, -1.0, 1.0])),
    torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),  # about (1, 1, 0)
    torch.tensor([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),  # about (0, 1, 1)
]
ROT_Z90 = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------------------------
# quat_to_rotmat
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_to_rotmat_is_a_rotation(dtype, seed, shape):
    R = quat_to_rotmat(unit_quats(seed, shape, dtype))
    assert R.shape == (*shape, 3, 3) and R.dtype == dtype
    assert_rotation(R, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_to_rotmat_sign_invariant_and_scale_invariant(dtype, seed, shape):
    q = unit_quats(seed, shape, dtype)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(quat_to_rotmat(-q), R, atol=ATOL[dtype], rtol=0)
    # documented: non-unit quaternions are treated as their normalisation
    torch.testing.assert_close(quat_to_rotmat(2.5 * q), R, atol=ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_to_rotmat_agrees_with_scipy(dtype, seed, shape):
    q = unit_quats(seed, shape, dtype)
    R = quat_to_rotmat(q).to(torch.float64)
    torch.testing.assert_close(R, scipy_rotmat(q), atol=ATOL[dtype], rtol=0)


def test_quat_to_rotmat_is_active_rotation():
    # 90 degrees about z maps e_x to e_y (active, right-handed).
    q = torch.tensor([0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)], dtype=torch.float64)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(
        R @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
        torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
    )
    torch.testing.assert_close(quat_to_rotmat(torch.tensor([0.0, 0.0, 0.0, 1.0])), torch.eye(3))


# ---------------------------------------------------------------------------------------------
# rotmat_to_quat
# ---------------------------------------------------------------------------------------------


def check_rotmat_to_quat(R: torch.Tensor, q_true: torch.Tensor | None, atol: float) -> None:
    q = rotmat_to_quat(R)
    assert q.shape == (*R.shape[:-2], 4) and q.dtype == R.dtype
    torch.testing.assert_close(
        q.norm(dim=-1), torch.ones(q.shape[:-1], dtype=q.dtype), atol=atol, rtol=0
    )
    assert (q[..., 3] >= 0).all()
    torch.testing.assert_close(quat_to_rotmat(q), R, atol=atol, rtol=0)
    if q_true is not None:
        assert_same_quat(q, q_true.to(q.dtype), atol)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_rotmat_to_quat_round_trip(dtype, seed, shape):
    q_true = unit_quats(seed, shape, torch.float64)
    check_rotmat_to_quat(scipy_rotmat(q_true).to(dtype), q_true, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_rotmat_to_quat_at_exactly_180_degrees(dtype, seed, shape):
    axis = unit_axes(seed, shape)
    q_true = torch.cat((axis, torch.zeros((*shape, 1), dtype=torch.float64)), dim=-1)
    check_rotmat_to_quat(scipy_rotmat(q_true).to(dtype), q_true, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes, delta=st.floats(min_value=0.0, max_value=1e-6))
def test_rotmat_to_quat_within_1e6_of_180_degrees(dtype, seed, shape, delta):
    axis = unit_axes(seed, shape)
    q_true = quat_of_angle_axis(torch.full(shape, math.pi - delta, dtype=torch.float64), axis)
    check_rotmat_to_quat(scipy_rotmat(q_true).to(dtype), q_true, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("R", [torch.eye(3), *EXACT_180], ids=lambda _: "")
def test_rotmat_to_quat_exact_special_matrices(dtype, R):
    R = R.to(dtype)
    check_rotmat_to_quat(R, None, ATOL[dtype])
    q = rotmat_to_quat(R)
    if torch.equal(R, torch.eye(3, dtype=dtype)):
        assert torch.equal(q, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype))
    else:
        assert q[3].item() == 0.0  # exactly 180 degrees: w is exactly 0, not a rounding residue


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_rotmat_to_quat_tiny_angles(dtype, seed, shape):
    axis = unit_axes(seed, shape)
    q_true = quat_of_angle_axis(torch.full(shape, 1e-8, dtype=torch.float64), axis)
    check_rotmat_to_quat(scipy_rotmat(q_true).to(dtype), q_true, ATOL[dtype])


# ---------------------------------------------------------------------------------------------
# quat_canonical
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_canonical_idempotent_same_rotation_nonneg_w(dtype, seed, shape):
    q = unit_quats(seed, shape, dtype)
    c = quat_canonical(q)
    assert torch.equal(quat_canonical(c), c)
    assert (c[..., 3] >= 0).all()
    # a sign flip of q: exactly q or exactly -q, hence the same rotation
    assert bool(((c == q).all(-1) | (c == -q).all(-1)).all())
    torch.testing.assert_close(quat_to_rotmat(c), quat_to_rotmat(q), atol=ATOL[dtype], rtol=0)
    assert torch.equal(quat_canonical(-q), c)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes, zeros=st.integers(min_value=1, max_value=3))
def test_quat_canonical_tie_w_zero_is_deterministic(dtype, seed, shape, zeros):
    # w == 0 (and possibly x == 0, y == 0): q and -q must give the same canonical output
    q = unit_quats(seed, shape, dtype).clone()
    q[..., 3] = 0.0
    q[..., : zeros - 1] = 0.0
    c = quat_canonical(q)
    assert torch.equal(quat_canonical(-q), c)
    assert torch.equal(quat_canonical(c), c)
    # documented rule: the first nonzero component in the order w, x, y, z is positive
    assert (c[..., zeros - 1] > 0).all()


# ---------------------------------------------------------------------------------------------
# quat_multiply / quat_inverse
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_multiply_composes_rotations(dtype, seed, shape):
    p, q = unit_quats(seed, (2, *shape), dtype).unbind(0)
    torch.testing.assert_close(
        quat_to_rotmat(quat_multiply(p, q)),
        quat_to_rotmat(p) @ quat_to_rotmat(q),
        atol=ATOL[dtype],
        rtol=0,
    )
    # Hamilton convention, against scipy's composition (r_p * r_q applies q first)
    ref = (
        Rotation.from_quat(p.double().reshape(-1, 4).numpy())
        * Rotation.from_quat(q.double().reshape(-1, 4).numpy())
    ).as_quat()
    ref_t = torch.from_numpy(ref).reshape(*shape, 4)
    assert_same_quat(quat_multiply(p, q).double(), ref_t, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_multiply_associative(dtype, seed, shape):
    p, q, r = unit_quats(seed, (3, *shape), dtype).unbind(0)
    torch.testing.assert_close(
        quat_multiply(quat_multiply(p, q), r),
        quat_multiply(p, quat_multiply(q, r)),
        atol=ATOL[dtype],
        rtol=0,
    )


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes, scale=st.floats(min_value=0.1, max_value=10.0))
def test_quat_inverse(dtype, seed, shape, scale):
    q = scale * unit_quats(seed, shape, dtype)  # also non-unit quaternions
    identity = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype).expand(*shape, 4)
    torch.testing.assert_close(
        quat_multiply(q, quat_inverse(q)), identity, atol=ATOL[dtype], rtol=0
    )
    torch.testing.assert_close(
        quat_multiply(quat_inverse(q), q), identity, atol=ATOL[dtype], rtol=0
    )


# ---------------------------------------------------------------------------------------------
# so3_exp / so3_log / hat / vee
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_hat_vee_inverse(dtype, seed, shape):
    phi, v = randn(seed, (2, *shape, 3), dtype).unbind(0)
    S = hat(phi)
    assert torch.equal(S, -S.transpose(-1, -2))
    torch.testing.assert_close(vee(S), phi, atol=0, rtol=0)
    torch.testing.assert_close(hat(vee(S)), S, atol=0, rtol=0)
    torch.testing.assert_close(
        (S @ v.unsqueeze(-1)).squeeze(-1), torch.linalg.cross(phi, v), atol=ATOL[dtype], rtol=0
    )
    # vee reads only the skew-symmetric part
    M = randn(seed + 1, (*shape, 3, 3), dtype)
    torch.testing.assert_close(
        vee(M + M.transpose(-1, -2)), torch.zeros_like(phi), atol=ATOL[dtype], rtol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_so3_log_exp_round_trip_below_pi(dtype, seed, shape):
    # angles in [0, pi - 1e-3): Log(Exp(phi)) = phi (the principal branch)
    theta = torch.rand(shape, generator=gen(seed), dtype=torch.float64) * (math.pi - 1e-3)
    phi = (theta.unsqueeze(-1) * unit_axes(seed + 1, shape)).to(dtype)
    torch.testing.assert_close(so3_log(so3_exp(phi)), phi, atol=10 * ATOL[dtype], rtol=0)
    torch.testing.assert_close(so3_log_quat(so3_exp_quat(phi)), phi, atol=ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("theta", [0.0, 1e-8, 1e-6, 1e-4, 1e-2])
def test_so3_log_exp_round_trip_small_angles(dtype, theta):
    axis = unit_axes(0, (16,))
    phi = (theta * axis).to(dtype)
    # relative accuracy, so that tiny angles are not just "close to zero"
    torch.testing.assert_close(so3_log(so3_exp(phi)), phi, atol=0, rtol=1e-4)


@pytest.mark.parametrize("theta", [1e-5, 1.9e-4, 1.99e-4, 2.01e-4, 3e-4])
def test_so3_log_series_branch_float64(theta):
    # around the switch to the series at |xyz| = 1e-4 (angle 2e-4): both sides accurate to
    # rounding (the matrix path loses ~1e-16 / theta relative in r21 - r12; bound 1e-10)
    phi = theta * unit_axes(5, (16,))
    torch.testing.assert_close(so3_log_quat(so3_exp_quat(phi)), phi, atol=0, rtol=1e-13)
    torch.testing.assert_close(so3_log(so3_exp(phi)), phi, atol=0, rtol=1e-10)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_so3_exp_log_round_trip(dtype, seed, shape):
    R = rotmats(seed, shape, dtype)
    phi = so3_log(R)
    assert phi.shape == (*shape, 3)
    assert (phi.norm(dim=-1) <= math.pi + ATOL[dtype]).all()
    torch.testing.assert_close(so3_exp(phi), R, atol=10 * ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes, theta=st.sampled_from([0.0, 1e-8, math.pi]))
def test_so3_exp_log_special_angles(dtype, seed, shape, theta):
    # exactly 0, tiny, and exactly pi (quaternion w = cos(pi/2) rounded, so w = 0 is set exactly)
    q = quat_of_angle_axis(torch.full(shape, theta, dtype=torch.float64), unit_axes(seed, shape))
    if theta == math.pi:
        q[..., 3] = 0.0
    R = scipy_rotmat(q).to(dtype)
    phi = so3_log(R)
    torch.testing.assert_close(
        phi.norm(dim=-1).double(),
        torch.full(shape, theta, dtype=torch.float64),
        atol=ATOL[dtype],
        rtol=0,
    )
    torch.testing.assert_close(so3_exp(phi), R, atol=ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("R", [torch.eye(3), *EXACT_180], ids=lambda _: "")
def test_so3_exp_log_exact_special_matrices(dtype, R):
    R = R.to(dtype)
    phi = so3_log(R)
    expected = 0.0 if torch.equal(R, torch.eye(3, dtype=dtype)) else math.pi
    assert abs(phi.norm().item() - expected) <= ATOL[dtype]
    torch.testing.assert_close(so3_exp(phi), R, atol=ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes, scale=st.floats(min_value=0.0, max_value=2 * math.pi))
def test_so3_exp_agrees_with_scipy(dtype, seed, shape, scale):
    phi = (scale * unit_axes(seed, shape)).to(dtype)
    ref = Rotation.from_rotvec(phi.double().reshape(-1, 3).numpy())
    R_ref = torch.from_numpy(ref.as_matrix()).reshape(*shape, 3, 3)
    torch.testing.assert_close(so3_exp(phi).double(), R_ref, atol=ATOL[dtype], rtol=0)
    q_ref = torch.from_numpy(ref.as_quat()).reshape(*shape, 4)
    assert_same_quat(so3_exp_quat(phi).double(), q_ref, ATOL[dtype])


# ---------------------------------------------------------------------------------------------
# angle / distances
# ---------------------------------------------------------------------------------------------


def scipy_angle(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """|Log(R1^T R2)| from scipy, float64."""
    shape = R1.shape[:-2]
    r1 = Rotation.from_matrix(R1.double().reshape(-1, 3, 3).numpy())
    r2 = Rotation.from_matrix(R2.double().reshape(-1, 3, 3).numpy())
    return torch.from_numpy((r1.inv() * r2).magnitude()).reshape(shape)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_angle_properties(dtype, seed, shape):
    R1, R2 = rotmats(seed, (2, *shape), dtype).unbind(0)
    t = angle(R1, R2)
    assert t.shape == shape and t.dtype == dtype
    torch.testing.assert_close(angle(R2, R1), t, atol=ATOL[dtype], rtol=0)
    assert ((t >= 0) & (t <= math.pi)).all()
    # equals |Log(R1^T R2)|, with rotlearn's log and with scipy
    torch.testing.assert_close(
        so3_log(R1.transpose(-1, -2) @ R2).norm(dim=-1), t, atol=10 * ATOL[dtype], rtol=0
    )
    torch.testing.assert_close(t.double(), scipy_angle(R1, R2), atol=10 * ATOL[dtype], rtol=0)
    torch.testing.assert_close(angle_deg(R1, R2), torch.rad2deg(t), atol=0, rtol=0)
    # zero on identical inputs (no acos: not even sqrt(eps) of rounding noise)
    assert (angle(R1, R1).abs() <= ATOL[dtype]).all()


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes, theta=st.floats(min_value=0.0, max_value=math.pi))
def test_angle_recovers_the_angle(dtype, seed, shape, theta):
    axis = unit_axes(seed, shape)
    R1 = rotmats(seed + 1, shape, torch.float64)
    R2 = R1 @ scipy_rotmat(quat_of_angle_axis(torch.full(shape, theta, dtype=torch.float64), axis))
    t = angle(R1.to(dtype), R2.to(dtype))
    torch.testing.assert_close(
        t.double(), torch.full(shape, theta, dtype=torch.float64), atol=10 * ATOL[dtype], rtol=0
    )
    torch.testing.assert_close(
        angle_deg(R1.to(dtype), R2.to(dtype)).double(),
        torch.full(shape, math.degrees(theta), dtype=torch.float64),
        atol=1e3 * ATOL[dtype],
        rtol=0,
    )


@pytest.mark.parametrize("theta", [1e-5, 1e-7, math.pi - 1e-5, math.pi - 1e-7, math.pi])
def test_angle_accurate_near_0_and_pi_float64(theta):
    axis = unit_axes(3, (32,))
    q = quat_of_angle_axis(torch.full((32,), theta, dtype=torch.float64), axis)
    if theta == math.pi:
        q[..., 3] = 0.0
    R1 = rotmats(4, (32,), torch.float64)
    R2 = R1 @ scipy_rotmat(q)
    t = angle(R1, R2)
    err = (t - theta).abs()
    if theta < 1:
        assert (err / theta).max().item() < 1e-3  # acos would give ~1e-8 absolute, i.e. 100%
    else:
        assert err.max().item() < 1e-9


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_chordal_distance_sq_is_8_sin2_half_angle(dtype, seed, shape):
    R1, R2 = rotmats(seed, (2, *shape), dtype).unbind(0)
    t = angle(R1, R2)
    d2 = chordal_distance_sq(R1, R2)
    torch.testing.assert_close(d2, 8 * torch.sin(t / 2) ** 2, atol=10 * ATOL[dtype], rtol=0)
    torch.testing.assert_close(d2, ((R1 - R2) ** 2).sum((-1, -2)), atol=ATOL[dtype], rtol=0)
    torch.testing.assert_close(chordal_distance(R1, R2), d2.sqrt(), atol=ATOL[dtype], rtol=0)
    assert ((d2 >= 0) & (d2 <= 8 + ATOL[dtype])).all()


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_quat_chordal_distance_relation(dtype, seed, shape):
    q1, q2 = unit_quats(seed, (2, *shape), dtype).unbind(0)
    d = quat_chordal_distance(q1, q2)
    assert ((d >= 0) & (d <= math.sqrt(2) + ATOL[dtype])).all()
    torch.testing.assert_close(quat_chordal_distance(q1, -q2), d, atol=0, rtol=0)
    torch.testing.assert_close(quat_chordal_distance(q2, q1), d, atol=ATOL[dtype], rtol=0)
    # paper footnote 3: |R(q1) - R(q2)|_F^2 = 2 d^2 (4 - d^2)
    lhs = chordal_distance_sq(quat_to_rotmat(q1), quat_to_rotmat(q2))
    torch.testing.assert_close(lhs, 2 * d**2 * (4 - d**2), atol=10 * ATOL[dtype], rtol=0)


# ---------------------------------------------------------------------------------------------
# sampling
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(seed=seeds, shape=shapes)
def test_random_rotations_are_rotations_and_reproducible(dtype, seed, shape):
    R = random_rotmat(shape, generator=gen(seed), dtype=dtype)
    assert R.shape == (*shape, 3, 3) and R.dtype == dtype
    assert_rotation(R, ATOL[dtype])
    assert torch.equal(random_rotmat(shape, generator=gen(seed), dtype=dtype), R)
    q = random_quat(shape, generator=gen(seed), dtype=dtype)
    torch.testing.assert_close(
        q.norm(dim=-1), torch.ones(shape, dtype=dtype), atol=ATOL[dtype], rtol=0
    )
    assert (q[..., 3] >= 0).all()
    v = random_unit_vectors(shape, 3, generator=gen(seed), dtype=dtype)
    torch.testing.assert_close(
        v.norm(dim=-1), torch.ones(shape, dtype=dtype), atol=ATOL[dtype], rtol=0
    )
    Ru = random_rotmat_uniform_angle(shape, 0.5, generator=gen(seed), dtype=dtype)
    assert_rotation(Ru, ATOL[dtype])
    assert (angle(Ru, torch.eye(3, dtype=dtype)) <= 0.5 + ATOL[dtype]).all()


def test_different_seeds_give_different_rotations():
    a = random_rotmat((8,), generator=gen(1), dtype=torch.float64)
    b = random_rotmat((8,), generator=gen(2), dtype=torch.float64)
    assert not torch.allclose(a, b)


@pytest.mark.parametrize("dtype", DTYPES)
@PROPS
@given(
    seed=seeds,
    shape=shapes,
    max_angle=st.floats(min_value=1e-6, max_value=math.pi),
)
def test_random_rotvec_uniform_angle_range_and_reproducible(dtype, seed, shape, max_angle):
    phi = random_rotvec_uniform_angle(shape, max_angle, generator=gen(seed), dtype=dtype)
    assert phi.shape == (*shape, 3) and phi.dtype == dtype
    norms = phi.norm(dim=-1)
    # [0, max_angle): the norm of axis * u * max_angle, up to the rounding of |axis| = 1
    assert (norms >= 0).all()
    assert (norms < max_angle * (1 + 8 * torch.finfo(dtype).eps)).all()
    again = random_rotvec_uniform_angle(shape, max_angle, generator=gen(seed), dtype=dtype)
    assert torch.equal(again, phi)


@pytest.mark.parametrize("max_angle", [0.0, -0.1, -math.pi, math.pi + 1e-6, 3.5, 2 * math.pi])
def test_random_rotvec_uniform_angle_rejects_bad_max_angle(max_angle):
    with pytest.raises(ValueError):
        random_rotvec_uniform_angle((4,), max_angle)


def test_random_rotvec_uniform_angle_accepts_pi():
    phi = random_rotvec_uniform_angle((1000,), math.pi, generator=gen(0))
    assert (phi.norm(dim=-1) <= math.pi * (1 + 1e-6)).all()


N_STAT = 200_000


def test_haar_rotation_angles_statistics():
    """Haar measure on SO(3): angle density (1 - cos t) / pi on [0, pi].

    Mean pi/2 + 2/pi, variance pi^2/12 - 4/pi^2; P(t < pi/2) = (pi/2 - 1)/pi; E[R] = 0 with
    entry variance 1/3. Each check allows 5 standard errors (two-sided p ~ 6e-7).
    """
    R = random_rotmat((N_STAT,), generator=gen(12345), dtype=torch.float64)
    t = angle(R, torch.eye(3, dtype=torch.float64))
    mean = math.pi / 2 + 2 / math.pi
    sd = math.sqrt(math.pi**2 / 12 - 4 / math.pi**2)
    assert abs(t.mean().item() - mean) < 5 * sd / math.sqrt(N_STAT)
    assert abs(t.std().item() - sd) < 0.01  # sd of the sample sd ~ 0.0008
    p = (math.pi / 2 - 1) / math.pi
    frac = (t < math.pi / 2).double().mean().item()
    assert abs(frac - p) < 5 * math.sqrt(p * (1 - p) / N_STAT)
    # uniform-angle sampling with max_angle = pi would have mean pi/2: well separated from this
    assert abs(mean - math.pi / 2) > 100 * sd / math.sqrt(N_STAT)
    assert R.mean(0).abs().max().item() < 5 * math.sqrt(1 / 3 / N_STAT)


@pytest.mark.parametrize("max_angle", [0.3, math.pi / 2, math.pi])
def test_uniform_angle_sampling_statistics(max_angle):
    """Angle ~ U[0, max_angle): mean max_angle/2, sd max_angle/sqrt(12); axis mean 0 (5 SE)."""
    phi = random_rotvec_uniform_angle((N_STAT,), max_angle, generator=gen(777), dtype=torch.float64)
    t = phi.norm(dim=-1)
    se = max_angle / math.sqrt(12) / math.sqrt(N_STAT)
    assert abs(t.mean().item() - max_angle / 2) < 5 * se
    axis = phi / t.unsqueeze(-1)
    assert axis.mean(0).abs().max().item() < 5 * math.sqrt(1 / 3 / N_STAT)
    # the matrix version has the same angles (Exp then angle to the identity)
    R = random_rotmat_uniform_angle((N_STAT,), max_angle, generator=gen(777), dtype=torch.float64)
    torch.testing.assert_close(angle(R, torch.eye(3, dtype=torch.float64)), t, atol=1e-9, rtol=0)


# ---------------------------------------------------------------------------------------------
# batch shapes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_functions_accept_any_leading_shape(shape):
    dtype = torch.float64
    q, p = unit_quats(0, (2, *shape), dtype).unbind(0)
    R, R2 = rotmats(1, (2, *shape), dtype).unbind(0)
    phi = randn(2, (*shape, 3), dtype)
    assert quat_to_rotmat(q).shape == (*shape, 3, 3)
    assert rotmat_to_quat(R).shape == (*shape, 4)
    assert quat_canonical(q).shape == quat_normalize(q).shape == (*shape, 4)
    assert quat_multiply(p, q).shape == quat_inverse(q).shape == (*shape, 4)
    assert so3_exp(phi).shape == hat(phi).shape == (*shape, 3, 3)
    assert so3_log(R).shape == vee(R).shape == (*shape, 3)
    assert so3_exp_quat(phi).shape == (*shape, 4) and so3_log_quat(q).shape == (*shape, 3)
    for f in (angle, angle_deg, chordal_distance, chordal_distance_sq):
        assert f(R, R2).shape == shape
    assert quat_chordal_distance(p, q).shape == shape
    assert random_rotmat(shape).shape == (*shape, 3, 3)
    assert random_rotvec_uniform_angle(shape, 1.0).shape == (*shape, 3)
    # batched results equal the per-element results
    flat_R, flat_R2 = R.reshape(-1, 3, 3), R2.reshape(-1, 3, 3)
    per = torch.stack([angle(a, b) for a, b in zip(flat_R, flat_R2, strict=True)])
    torch.testing.assert_close(angle(R, R2).reshape(-1), per.reshape(-1))
    # broadcasting a single rotation against a batch
    assert angle(R, torch.eye(3, dtype=dtype)).shape == shape


# ---------------------------------------------------------------------------------------------
# gradients (float64 gradcheck)
# ---------------------------------------------------------------------------------------------

F64 = torch.float64


def test_gradcheck_quat_to_rotmat():
    q = (1.7 * randn(10, (5, 4), F64)).requires_grad_()  # non-unit too
    assert torch.autograd.gradcheck(quat_to_rotmat, (q,))


def generic_rotations_all_branches() -> torch.Tensor:
    """Rotations whose largest diagonal entry of K is x, y, z or w (each branch of the argmax)."""
    axes = unit_axes(11, (4,))
    near = torch.cat([2.8 * torch.eye(3, dtype=F64) + 0.2 * axes[:3], 0.5 * axes[3:]], dim=0)
    return so3_exp(near)


def test_gradcheck_rotmat_to_quat():
    R = generic_rotations_all_branches()
    K_diag = torch.stack(
        [
            1 + R[:, 0, 0] - R[:, 1, 1] - R[:, 2, 2],
            1 - R[:, 0, 0] + R[:, 1, 1] - R[:, 2, 2],
            1 - R[:, 0, 0] - R[:, 1, 1] + R[:, 2, 2],
            1 + R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2],
        ],
        -1,
    )
    assert sorted(K_diag.argmax(-1).tolist()) == [0, 1, 2, 3]
    assert torch.autograd.gradcheck(rotmat_to_quat, (R.clone().requires_grad_(),))


@pytest.mark.parametrize("norm", [0.0, 0.3, 2.0, math.pi - 1e-3, math.pi, math.pi + 1e-3])
def test_gradcheck_so3_exp(norm):
    phi = (norm * unit_axes(12, (3,))).requires_grad_()
    assert torch.autograd.gradcheck(so3_exp, (phi,))
    assert torch.autograd.gradcheck(so3_exp_quat, (phi,))


@pytest.mark.parametrize("theta", [1e-5, 0.5, 2.0, 3.0])
def test_gradcheck_so3_log(theta):
    q = quat_of_angle_axis(torch.full((4,), theta, dtype=F64), unit_axes(13, (4,)))
    R = scipy_rotmat(q).requires_grad_()
    assert torch.autograd.gradcheck(so3_log, (R,))


def test_gradcheck_angle_generic_pairs():
    R1, R2 = rotmats(14, (2, 4), F64).unbind(0)
    assert torch.autograd.gradcheck(angle, (R1.requires_grad_(), R2.requires_grad_()))


def test_gradcheck_angle_at_zero():
    R = rotmats(15, (4,), F64)
    R1, R2 = R.clone().requires_grad_(), R.clone().requires_grad_()
    assert torch.autograd.gradcheck(angle, (R1, R2))
    g1, g2 = torch.autograd.grad(angle(R1, R2).sum(), (R1, R2))
    assert torch.isfinite(g1).all() and torch.isfinite(g2).all()
    assert g1.abs().max().item() == 0.0 and g2.abs().max().item() == 0.0  # the subgradient 0


def exact_180_pairs(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs exactly 180 degrees apart with exactly representable entries (R1^T R2 exact)."""
    R2 = torch.stack(EXACT_180).to(dtype)
    R1 = torch.stack([torch.eye(3), ROT_Z90, ROT_Z90.T, ROT_Z90 @ ROT_Z90, torch.eye(3)]).to(dtype)
    return R1, R1 @ R2


def test_gradcheck_angle_at_180_degrees():
    R1, R2 = exact_180_pairs(F64)
    torch.testing.assert_close(angle(R1, R2), torch.full((5,), math.pi, dtype=F64))
    R1, R2 = R1.requires_grad_(), R2.requires_grad_()
    assert torch.autograd.gradcheck(angle, (R1, R2))
    g1, g2 = torch.autograd.grad(angle(R1, R2).sum(), (R1, R2))
    assert torch.isfinite(g1).all() and torch.isfinite(g2).all()


def test_angle_gradient_finite_float32():
    R = rotmats(16, (8,), torch.float32)
    R1 = R.clone().requires_grad_()
    (g,) = torch.autograd.grad(angle(R1, R).sum(), R1)
    assert torch.isfinite(g).all()
    # exactly representable 180-degree pairs
    A, B = exact_180_pairs(torch.float32)
    A = A.requires_grad_()
    (g,) = torch.autograd.grad(angle(A, B).sum(), A)
    assert torch.isfinite(g).all()
    # 180 degrees up to rounding (R1^T R2 not exact): still finite
    q = torch.cat((unit_axes(17, (8,)), torch.zeros(8, 1, dtype=F64)), -1)
    R2 = (R.double() @ scipy_rotmat(q)).float()
    (g,) = torch.autograd.grad(angle(R1, R2).sum(), R1)
    assert torch.isfinite(g).all()
