"""Datamodules whose loaders yield draw requests; the data is made on the model's device.

A loader yields small dicts {"draw_split", "draw_index", "draw_size", "draw_like"}; `finish_batch`
turns each into a batch with `draw(split, index, size, device, dtype)`, from a generator seeded by
(data seed, split, epoch, index). So a run is reproducible, a resumed run sees the same data, and a
learning-rate sweep sees the same data.

The device and dtype are given by the caller, or, in Lightning's `on_after_batch_transfer`, read
from the request's own 0-d float tensor `draw_like`: Lightning's precision plugin casts it to the
model's input dtype and the transfer puts it on the model's device. Data never asks the model.
"""

from __future__ import annotations

from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader

__all__ = ["SPLITS", "DrawDataModule", "draw_seed"]

SPLITS = {"train": 0, "val": 1, "test": 2}


def draw_seed(*words: int) -> int:
    """A well-mixed 63-bit seed from a tuple of non-negative integers."""
    return int(np.random.SeedSequence(list(words)).generate_state(1, np.uint64)[0] >> 1)


class DrawDataModule(pl.LightningDataModule):
    """Base class: subclasses set `seed` and `redraw_test` and implement `draw`."""

    seed: int = 0
    redraw_test: bool = False

    def requests(self, split: str, sizes: list[int]) -> DataLoader:
        """A loader of one draw request per batch size in `sizes`."""
        items = [
            {"draw_split": SPLITS[split], "draw_index": i, "draw_size": n,
             "draw_like": torch.zeros(())}
            for i, n in enumerate(sizes)
        ]  # fmt: skip
        return DataLoader(items, batch_size=None, shuffle=False, num_workers=0)

    def finish_batch(
        self,
        batch: Any,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> Any:
        """The batch a loader item names, made on `device` in `dtype`: the one step from a loader
        item to what the model sees (Lightning's hook, the init callback and scripts call it).

        Args:
            batch: a draw request (anything else is returned as it is).
            device, dtype: where and in which float dtype to make the data; None: those of the
                request's `draw_like` tensor (CPU, float32 for a request that was not moved).

        Returns:
            {"input", "R" (size, 3, 3), "q" (size, 4) (x, y, z, w)} on `device`, in `dtype`.
        """
        if not (isinstance(batch, dict) and "draw_split" in batch):
            return batch
        like = batch.get("draw_like", torch.zeros(()))
        device = torch.device(device) if device is not None else like.device
        dtype = dtype if dtype is not None else like.dtype
        split, index, size = (int(batch[k]) for k in ("draw_split", "draw_index", "draw_size"))
        return self.draw(split, index, size, device, dtype)

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """`finish_batch` on the device and in the dtype the transfer gave the request."""
        return self.finish_batch(batch)

    def draw(
        self,
        split: int,
        index: int,
        size: int,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> dict[str, Tensor]:  # pragma: no cover
        raise NotImplementedError

    def generator(self, split: int, index: int, device: torch.device) -> torch.Generator:
        """The seeded generator for a request whose data is made on `device`.

        Training draws are redrawn every epoch, on `device`. Validation and test draws are fixed
        (unless `redraw_test`) and made on the CPU, so they are the same on every device.
        """
        trainer = self.trainer
        epoch = trainer.current_epoch if trainer is not None else 0
        fixed = split != SPLITS["train"] and not self.redraw_test
        seed = draw_seed(self.seed, split, 0 if fixed else epoch + 1, index)
        gen_device = torch.device("cpu") if fixed else device
        return torch.Generator(device=gen_device).manual_seed(seed)
