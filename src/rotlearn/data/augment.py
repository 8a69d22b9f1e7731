"""Training-time augmentation of image pairs: drawn in the training loader, applied in the one
finishing step (`ImagePairDataModule.finish_batch`).

The training loader's dataset (`AugmentedPairs`) adds to each batch what to do to each pair:
"swap" (B,) bool and "jitter" (B, 2) float (brightness and contrast factors), drawn from a
generator seeded by the data seed and the batch's pair indices (so the same seed and shuffle give
the same draws, with or without loader workers). Validation and test loaders never carry these
keys, so their batches are never augmented.

- Pair swap: the frames (1, 2) become (2, 1), so the target C_21 becomes C_12 = C_21^T and its
  quaternion the conjugate (x, y, z, w) -> (-x, -y, -z, w).
- Photometric jitter, the same factors for both frames of a pair: pixels x in [0, 1] become
  clamp(c * (b * x) + (1 - c) * mean(b * x), 0, 1), the mean over each frame's channels and
  pixels (torchvision's ColorJitter brightness then contrast). One draw per pair, not per frame:
  the two frames come from one camera a fraction of a second apart, and the pair network matches
  them by their appearance; independent jitter would teach it to ignore the brightness it
  matches on, for exposure changes between frames that the demo data never has.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import Dataset

from rotlearn.data.draws import SPLITS, draw_seed
from rotlearn.errors import ConfigError

__all__ = ["AugmentedPairs", "apply_jitter", "check_photometric", "swap_pairs"]

PHOTOMETRIC_KEYS = ("brightness", "contrast")


def check_photometric(photometric: Mapping[str, float] | None) -> dict[str, float]:
    """{"brightness": b, "contrast": c}, each in [0, 1) (0: off), from the config value.

    Raises:
        ConfigError: on `photometric`, for another key or a value out of range.
    """
    if photometric is None:
        return {key: 0.0 for key in PHOTOMETRIC_KEYS}
    if not isinstance(photometric, Mapping):
        raise ConfigError("photometric", f"must be a mapping or null, got {photometric!r}")
    unknown = sorted(set(photometric) - set(PHOTOMETRIC_KEYS))
    if unknown:
        raise ConfigError("photometric", f"unknown key(s) {unknown}; allowed: brightness, contrast")
    values = {key: photometric.get(key, 0.0) for key in PHOTOMETRIC_KEYS}
    for key, value in values.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value < 1:
            raise ConfigError(f"photometric.{key}", f"must be a number in [0, 1), got {value!r}")
    return {key: float(value) for key, value in values.items()}


def swap_pairs(images: Tensor, R: Tensor, q: Tensor, swap: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The pairs flagged in `swap` with their two frames exchanged and their targets inverted.

    Args:
        images: (B, 2C, S, S) stacked pairs (frame 1 in the first C channels), any dtype.
        R: (B, 3, 3) targets C_21.
        q: (B, 4) their quaternions (x, y, z, w).
        swap: (B,) bool.

    Returns:
        images, R, q: swapped rows hold (frame 2, frame 1), C_21^T and the conjugate of q.
    """
    channels = images.shape[1] // 2
    s = swap.to(images.device, torch.bool)
    images = torch.where(s[:, None, None, None], images.roll(channels, dims=1), images)
    R = torch.where(s[:, None, None], R.mT, R)
    conjugate = q * q.new_tensor([-1.0, -1.0, -1.0, 1.0])
    return images, R, torch.where(s[:, None], conjugate, q)


def apply_jitter(x: Tensor, jitter: Tensor, channels: int) -> Tensor:
    """Brightness then contrast jitter of pairs with pixels in [0, 1] (module docstring).

    Args:
        x: (B, 2C, S, S) floats in [0, 1].
        jitter: (B, 2) brightness and contrast factors, one pair of factors for both frames.
        channels: C, the channels of one frame.

    Returns:
        (B, 2C, S, S) in x's dtype, clamped to [0, 1].
    """
    B, _, H, W = x.shape
    frames = x.view(B, 2, channels, H, W)
    b, c = (jitter[:, i].to(x.dtype)[:, None, None, None, None] for i in range(2))
    bright = frames * b
    mean = bright.mean(dim=(2, 3, 4), keepdim=True)
    return torch.lerp(mean, bright, c).clamp_(0.0, 1.0).view_as(x)


class AugmentedPairs(Dataset):
    """The training pairs, each batch with its draws: "swap" (B,) bool (probability `swap`; only
    where `swap` > 0) and "jitter" (B, 2) (brightness factor in [1 - b, 1 + b], contrast factor in
    [1 - c, 1 + c], uniform; only where b or c > 0), from a generator seeded by (`seed`, the
    batch's pair indices); the same draws whichever of them is on.

    Args:
        pairs: a dataset with `__getitems__` (`rotlearn.data.pairs.ImagePairs`).
        swap: probability of swapping a pair, in [0, 1].
        photometric: {"brightness": b, "contrast": c} (`check_photometric`).
        seed: the data seed.
    """

    def __init__(
        self, pairs: Any, swap: float, photometric: Mapping[str, float], seed: int
    ) -> None:
        self.pairs, self.swap, self.seed = pairs, float(swap), int(seed)
        self.photometric = dict(photometric)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitems__(self, indices: list[int]) -> dict[str, Tensor]:
        batch = self.pairs.__getitems__(indices)
        n = len(indices)
        seed = draw_seed(self.seed, SPLITS["train"], 17, *(int(i) for i in indices))
        generator = torch.Generator().manual_seed(seed)
        draws = torch.rand(n, 3, generator=generator)
        half = torch.tensor([self.photometric["brightness"], self.photometric["contrast"]])
        if self.swap > 0:
            batch["swap"] = draws[:, 0] < self.swap
        if half.any():
            batch["jitter"] = 1.0 + (2.0 * draws[:, 1:] - 1.0) * half
        return batch

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {k: v[0] for k, v in self.__getitems__([i]).items()}
