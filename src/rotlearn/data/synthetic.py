"""Synthetic Wahba problem (paper section VI-A, eq. 27): unit vectors u_i and v_i = R u_i + eps_i.

Batches are drawn on the model's device (see `rotlearn.data.draws`). Optionally heteroscedastic
(issue 17): each sample draws its own noise level and number of distinct matches
(`rotlearn.data.heteroscedastic`), so a good belief must widen for hard samples.
"""

from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING, Annotated

import torch
from torch import Tensor
from torch.utils.data import DataLoader

from rotlearn.data.draws import DrawDataModule
from rotlearn.data.heteroscedastic import (
    check_range,
    difficulty,
    log_uniform,
    repeat_rows,
    uniform_counts,
)
from rotlearn.errors import ConfigError, InputAdjustedWarning
from rotlearn.geometry import (
    quat_to_rotmat,
    random_rotvec_uniform_angle,
    random_unit_vectors,
    so3_exp_quat,
)
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Ge, Gt, Le

__all__ = ["MIN_MATCHES", "SyntheticWahbaDataModule", "wahba_batch"]

MIN_MATCHES = 2  # two non-parallel pairs (u_i, v_i) fix the rotation (random u_i: almost surely)


def wahba_batch(
    batch_size: int,
    num_matches: int,
    max_angle: float,
    sigma: float,
    *,
    sigma_range: tuple[float, float] | None = None,
    matches_range: tuple[int, int] | None = None,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> dict[str, Tensor]:
    """One batch of Wahba problems.

    R = Exp(phi a / |a|) with a ~ N(0, I), phi ~ U[0, max_angle); u_i uniform on S^2;
    v_i = R u_i + eps_i, eps_i ~ N(0, sigma^2 I) (paper eq. 27).

    Heteroscedastic data (either range given): sample b has its own noise level sigma_b,
    log-uniform in `sigma_range` (else `sigma`), and its own number n_b of distinct matches,
    uniform on the integers of `matches_range` (else N = `num_matches`). Its rows n_b, ..., N - 1
    repeat its own matches (row j is match j mod n_b, noise included), so the batch stays
    (B, N, 6) and a max-pooling net sees exactly n_b matches. Its "difficulty" sigma_b / sqrt(n_b)
    grows with the expected error of the best estimate (for small noise the least-squares
    estimate's angular error scales as sigma / sqrt(n)).

    Returns:
        {"input": (B, N, 6) rows (u_i, v_i), "R": (B, 3, 3), "q": (B, 4) (x, y, z, w), w >= 0};
        heteroscedastic data also "sigma" (B,), "num_matches" (B,) int64 and "difficulty" (B,).
        Homoscedastic data (both ranges None) omits them: every sample is equally hard, and the
        batch (values and keys) is the one this function always drew.
    """
    kw = {"generator": generator, "device": device, "dtype": dtype}
    q = so3_exp_quat(random_rotvec_uniform_angle((batch_size,), max_angle, **kw))
    R = quat_to_rotmat(q)
    u = random_unit_vectors((batch_size, num_matches), 3, **kw)
    noise = torch.randn(u.shape, generator=generator, device=u.device, dtype=dtype)
    if sigma_range is None and matches_range is None:
        v = u @ R.transpose(-1, -2) + sigma * noise
        return {"input": torch.cat((u, v), dim=-1), "R": R, "q": q}
    # drawn after the homoscedastic draws, so those stay the same for the same generator
    if sigma_range is not None:
        sigmas = log_uniform(batch_size, *sigma_range, generator=generator, device=u.device,
                             dtype=dtype)  # fmt: skip
    else:
        sigmas = torch.full((batch_size,), float(sigma), device=u.device, dtype=dtype)
    if matches_range is not None:
        counts = uniform_counts(batch_size, *matches_range, generator=generator, device=u.device)
    else:
        counts = torch.full((batch_size,), num_matches, device=u.device, dtype=torch.int64)
    v = u @ R.transpose(-1, -2) + sigmas[:, None, None] * noise
    points = repeat_rows(torch.cat((u, v), dim=-1), counts)
    return {
        "input": points,
        "R": R,
        "q": q,
        "sigma": sigmas,
        "num_matches": counts,
        "difficulty": difficulty(sigmas, counts),
    }


@config_target
class SyntheticWahbaDataModule(DrawDataModule):
    """Synthetic Wahba data (paper section VI-A), drawn batch by batch on the model's device.

    Training batches are redrawn every epoch (an epoch is `batches_per_epoch` batches). The
    validation and test sets are fixed by `seed` (drawn on the CPU, so identical on every device)
    unless `redraw_test`, which redraws them every epoch as the original code did.

    Args:
        phi_max_deg: maximum rotation angle in degrees, in (0, 180].
        sigma: standard deviation of the noise on v_i (every sample), unless `sigma_range`.
        num_matches: N, the number of matched vector pairs per sample (the tensor width); with
            `matches_range` it must equal the range's hi.
        sigma_range: [lo, hi] with 0 < lo <= hi: each sample's noise level is drawn log-uniformly
            in [lo, hi] (replaces `sigma`); null: every sample has `sigma`.
        matches_range: [lo, hi] integers with 2 <= lo <= hi = num_matches: each sample's number
            of distinct matches is uniform on lo..hi, its other rows repeat its own matches;
            null: every sample has `num_matches` distinct matches.
            With either range, batches carry "sigma", "num_matches" and "difficulty"
            (sigma / sqrt(n), see `wahba_batch`); without, they do not.
        batch_size: training batch size.
        batches_per_epoch: training batches per epoch.
        num_val: validation samples; num_test: test samples.
        eval_batch_size: batch size of the validation and test loaders.
        redraw_test: redraw validation and test sets every epoch.
        seed: the data seed (`data.seed`), independent of the model's `seed`.
    """

    def __init__(
        self,
        phi_max_deg: Annotated[float, Gt(0), Le(180)] = 180.0,
        sigma: Annotated[float, Ge(0)] = 0.01,
        num_matches: Annotated[int, Gt(0)] = 100,
        batch_size: Annotated[int, Gt(0)] = 100,
        batches_per_epoch: Annotated[int, Gt(0)] = 5,
        num_val: Annotated[int, Gt(0)] = 100,
        num_test: Annotated[int, Gt(0)] = 500,
        eval_batch_size: Annotated[int, Gt(0)] = 100,
        redraw_test: bool = False,
        seed: Annotated[int, Ge(0)] = 0,
        sigma_range: list[float] | None = None,
        matches_range: list[int] | None = None,
    ) -> None:
        super().__init__()
        self.sigma_range = check_range("sigma_range", sigma_range, minimum=0.0, strict=True)
        matches = check_range("matches_range", matches_range, minimum=MIN_MATCHES, integer=True)
        self.matches_range = None if matches is None else (int(matches[0]), int(matches[1]))
        if self.matches_range is not None and self.matches_range[1] != num_matches:
            raise ConfigError(
                "matches_range",
                f"hi ({self.matches_range[1]}) must equal num_matches ({num_matches}), the "
                "tensor width: set data.num_matches to the range's hi",
            )
        self.phi_max_deg = float(phi_max_deg)
        self.sigma = float(sigma)
        self.num_matches = int(num_matches)
        self.batch_size = int(batch_size)
        self.batches_per_epoch = int(batches_per_epoch)
        self.num_val, self.num_test = int(num_val), int(num_test)
        self.eval_batch_size = int(eval_batch_size)
        self.redraw_test = bool(redraw_test)
        self.seed = int(seed)

    @staticmethod
    def prepare_points(points: Tensor) -> Tensor:
        """Matched pairs (u_i, v_i) (..., N, 6) as the network was trained on them: each pair
        divided by |u_i|, so that u_i is a unit vector (a direction, as every training u_i is)
        and v_i = R u_i + noise keeps its relation to it (its length says how noisy it is).
        Warns (`InputAdjustedWarning`) how many u_i were not of unit length (within 1e-3): a
        network given longer vectors answers with a wrong rotation and a confident belief.

        Raises:
            ValueError: a u_i of length 0 (no direction), naming the first pair.
        """
        length = torch.linalg.vector_norm(points[..., :3], dim=-1, keepdim=True)  # (..., N, 1)
        if bool((length == 0).any()):
            first = tuple(int(i) for i in (length[..., 0] == 0).nonzero()[0])
            where = f"pair {first[-1]}" + (f" of input {first[0]}" if len(first) > 1 else "")
            raise ValueError(f"{where}: u_i = 0 has no direction (the network reads unit u_i)")
        scaled = int(((length - 1).abs() > 1e-3).sum())
        if scaled:
            warnings.warn(
                f"{scaled} of {length.numel()} u_i were not of unit length; each pair (u_i, v_i) "
                "was divided by |u_i|, as the network was trained on unit u_i",
                InputAdjustedWarning,
                stacklevel=4,  # the caller of Predictor.__call__ (under no_grad)
            )
        return points / length

    @staticmethod
    def _sizes(total: int, batch: int) -> list[int]:
        return [min(batch, total - start) for start in range(0, total, batch)]

    def train_dataloader(self) -> DataLoader:
        return self.requests("train", [self.batch_size] * self.batches_per_epoch)

    def val_dataloader(self) -> DataLoader:
        return self.requests("val", self._sizes(self.num_val, self.eval_batch_size))

    def test_dataloader(self) -> DataLoader:
        return self.requests("test", self._sizes(self.num_test, self.eval_batch_size))

    def draw(
        self,
        split: int,
        index: int,
        size: int,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> dict[str, Tensor]:
        """The batch a request names, made on `device` in `dtype`."""
        generator = self.generator(split, index, device)
        batch = wahba_batch(
            size,
            self.num_matches,
            math.radians(self.phi_max_deg),
            self.sigma,
            sigma_range=self.sigma_range,
            matches_range=self.matches_range,
            generator=generator,
            device=generator.device,
            dtype=dtype,
        )
        return {k: v.to(device, non_blocking=True) for k, v in batch.items()}
