"""What every representation head returns, and the registry that `rep=` picks from."""

from __future__ import annotations

from torch import Tensor, nn

from rotlearn.bingham.descriptors import (
    dispersion_from_eigenvalues,
    dt_from_eigenvalues,
    eigengap_from_eigenvalues,
)
from rotlearn.bingham.product import disagreement
from rotlearn.errors import ConfigError
from rotlearn.geometry import rotmat_to_quat
from rotlearn.trust import config_target

__all__ = ["HEADS", "RotationHead", "RotationPrediction", "make_head", "register_head"]


class RotationPrediction:
    """A head's output for a batch of shape (...).

    Attributes:
        R: (..., 3, 3) rotation matrices.
        raw: (..., out_dim) the network output the head was given.
        A: (..., 4, 4) symmetric matrices of the Bingham belief p(q) ~ exp(-q^T A q) (paper
            eqs. 8, 14) for heads that define a belief, else None. The Fisher head gives the
            Bingham matrix of its matrix Fisher belief (the same density on SO(3)).
        eigenvalues: (..., 4) ascending eigenvalues of A (belief heads only), else None.
        F: (..., 3, 3) matrix Fisher parameter, p(R) ~ exp(tr(F^T R)) (Fisher head only), else
            None.
        members: (K, ..., 4) the members' quaternions (x, y, z, w) of an ensemble
            (`rotlearn.heads.ensemble.EnsembleHead`: A is the sum of the members' A), else None.

    Heads with a belief also give its uncertainty (`dispersion`, `dt`, `eigengap`; None for the
    others), each from the one definition in `rotlearn.bingham.descriptors`; an ensemble also
    its members' `disagreement`.
    """

    __slots__ = ("A", "F", "R", "_q", "eigenvalues", "members", "raw")

    def __init__(
        self,
        R: Tensor,
        raw: Tensor,
        q: Tensor | None = None,
        A: Tensor | None = None,
        eigenvalues: Tensor | None = None,
        F: Tensor | None = None,
        members: Tensor | None = None,
    ) -> None:
        self.R, self.raw, self._q, self.A, self.eigenvalues = R, raw, q, A, eigenvalues
        self.F, self.members = F, members

    @property
    def q(self) -> Tensor:
        """(..., 4) unit quaternions (x, y, z, w), w >= 0; derived from R when the head has none."""
        if self._q is None:
            self._q = rotmat_to_quat(self.R)
        return self._q

    @property
    def dispersion(self) -> Tensor | None:
        """(..., 3) Bingham dispersion coefficients (l1 - l4, l1 - l3, l1 - l2) <= 0 (paper
        III-C); more negative = more concentrated. None without a belief."""
        return None if self.eigenvalues is None else dispersion_from_eigenvalues(self.eigenvalues)

    @property
    def dt(self) -> Tensor | None:
        """(...,) dispersion-thresholding score tr(Lambda) = 3 l1 - l2 - l3 - l4 <= 0 (paper
        eq. 26); lower = more confident. None without a belief."""
        return None if self.eigenvalues is None else dt_from_eigenvalues(self.eigenvalues)

    @property
    def eigengap(self) -> Tensor | None:
        """(...,) first eigen-gap l2 - l1 >= 0 (0: the mode is not unique). None without a
        belief."""
        return None if self.eigenvalues is None else eigengap_from_eigenvalues(self.eigenvalues)

    @property
    def disagreement(self) -> Tensor | None:
        """(...,) the largest angle in degrees between an ensemble member's rotation and the
        ensemble's (`rotlearn.bingham.disagreement`); None for a single model."""
        return None if self.members is None else disagreement(self.members, self.q)

    def detach(self) -> RotationPrediction:
        """The same prediction cut from the autograd graph."""

        def cut(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.detach()

        return RotationPrediction(
            self.R.detach(),
            self.raw.detach(),
            cut(self._q),
            cut(self.A),
            cut(self.eigenvalues),
            cut(self.F),
            cut(self.members),
        )

    def with_temperature(self, temperature: float | Tensor) -> RotationPrediction:
        """The same rotations with the belief tempered: A / T, eigenvalues / T, F / T.

        T > 1 widens the belief, T < 1 sharpens it (post-hoc calibration, `calibrate=true`);
        the mode (R, q) and the network output are unchanged. Without a belief, or with T = 1
        given as a Python number, the prediction itself is returned.
        """

        def scale(t: Tensor | None) -> Tensor | None:
            return None if t is None else t / temperature

        if self.A is None or (not isinstance(temperature, Tensor) and temperature == 1):
            return self
        return RotationPrediction(
            self.R, self.raw, self._q, scale(self.A), scale(self.eigenvalues), scale(self.F),
            self.members,
        )  # fmt: skip


class RotationHead(nn.Module):
    """A stateless map from a network output (..., out_dim) to a `RotationPrediction`."""

    name: str = ""
    out_dim: int = 0
    defines_belief: bool = False  # True where the output parameterises a Bingham density
    defines_fisher: bool = False  # True where it also gives a matrix Fisher parameter (F)
    defines_members: bool = False  # True for an ensemble: its members' rotations (`members`)

    def forward(self, raw: Tensor) -> RotationPrediction:  # pragma: no cover - interface
        raise NotImplementedError

    def extra_repr(self) -> str:
        return f"out_dim={self.out_dim}"


HEADS: dict[str, type[RotationHead]] = {}


def register_head(cls: type[RotationHead]) -> type[RotationHead]:
    """Class decorator: make a head available as `rep=<cls.name>`."""
    if cls.name in HEADS:
        raise ValueError(f"a head named {cls.name!r} is already registered")
    HEADS[cls.name] = cls
    return cls


@config_target
def make_head(name: str, out_dim: int | None = None, solver: str | None = None) -> RotationHead:
    """The head registered as `name` (the config's `rep.name`).

    Args:
        name: one of `HEADS`.
        out_dim: if given (the config's `rep.out_dim`), it must equal the head's output size.
        solver: the eigensolver of the A head (`rep.solver`: auto, jacobi or eigh; None: the
            head's default); other heads have none.

    Raises:
        ConfigError: unknown `name` (the message lists the allowed ones), or an `out_dim`
            that disagrees with the head.
    """
    if name not in HEADS:
        raise ConfigError("name", f"unknown rep {name!r}; allowed: {', '.join(sorted(HEADS))}")
    if solver is not None and name != "a":
        raise ConfigError("solver", f"only the 'a' head has a solver; rep={name} has none")
    head = HEADS[name]() if solver is None else HEADS[name](solver=solver)
    if out_dim is not None and out_dim != head.out_dim:
        raise ConfigError("out_dim", f"is {out_dim} but the {name!r} head outputs {head.out_dim}")
    return head
