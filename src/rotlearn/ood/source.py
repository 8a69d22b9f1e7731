"""What the OOD evaluation reads from a datamodule: a small declared protocol.

`rotlearn.data.ImagePairDataModule` (KITTI, MAV) implements it. Batches come as the loaders yield
them and are finished (device, dtype, erasing, normalisation) by the source's `finish_batch`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

__all__ = ["OODDataSource"]


@runtime_checkable
class OODDataSource(Protocol):
    """A datamodule the OOD evaluation can score (set up before use)."""

    def pair_count(self, split: str) -> int:
        """How many samples "train" or "test" holds."""
        ...

    def pair_shape(self) -> tuple[int, ...]:
        """The shape of one input, e.g. (2C, S, S) for a stacked image pair."""
        ...

    def eval_loader(
        self, split: str, indices: Sequence[int] | None = None, erase: Tensor | None = None
    ) -> Iterable[dict[str, Tensor]]:
        """Unshuffled evaluation batches of `split` (all samples, or those at `indices` in that
        order); `erase`: (N,) bool over the split, which samples are erased (None: the split's
        own flags)."""
        ...

    def unseen_pairs(self, split: str) -> Tensor:
        """(N,) bool: which samples of `split` come from sequences / scenes not trained on."""
        ...

    def noise_batch(self, n: int) -> dict[str, Tensor]:
        """A loader-style batch of `n` pure-noise inputs (seeded)."""
        ...

    def finish_batch(
        self, batch: Any, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Any:
        """A loader batch as the model sees it, on `device` in `dtype`."""
        ...

    def train_dataloader(self) -> Iterable[dict[str, Tensor]]:
        """The training batches (for training an auto-encoder on them)."""
        ...
