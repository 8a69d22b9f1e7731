"""Image-pair datasets over frame caches, and their LightningDataModule base (KITTI, MAV).

(Above 350 lines on purpose: the pair index, the dataset and the datamodule base share one batch
layout, documented once below; the augmentation itself lives in `rotlearn.data.augment`.)

A batch is {"input": (B, 2C, S, S) in the model's dtype, "R": (B, 3, 3), "q": (B, 4) (x, y, z, w),
"corrupted": (B,) bool, "source": (B,) int64 (sequence / scene index), "index": (B,) int64}
(training batches with augmentation also carry the loader's draws "swap" and "jitter",
`rotlearn.data.augment`, which the finishing step applies and removes).
Loader workers gather whole batches of uint8 frames from memory-mapped caches (`__getitems__`);
the conversion to floats, the training augmentation, the normalisation and the erasing of
corrupted test pairs happen after the transfer, on the model's device, in ONE step:
`ImagePairDataModule.finish_batch`, which Lightning's `on_after_batch_transfer` and every other
caller (the OOD evaluation, the data-dependent initialisation, benchmarks) use.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import lightning.pytorch as pl
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, get_worker_info

from rotlearn.data import augment
from rotlearn.data.corruption import corrupted_flags, draw_erasing_boxes, erase_boxes
from rotlearn.data.draws import SPLITS, draw_seed
from rotlearn.errors import ConfigError
from rotlearn.geometry import rotmat_to_quat

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Ge, Gt, Le, Lt

__all__ = ["ImagePairDataModule", "ImagePairs", "PairIndex"]

# The start method Python uses on this platform by default (the first listed), for loader workers.
_PLATFORM_START = multiprocessing.get_all_start_methods()[0]
# One loader batch of uint8 pairs at most (the model sees 4x that as float32): the paper's
# (64 pairs of 6 x 224 x 224) is 19 MB. A received run's config chooses the frame size and the
# batch of an evaluation; 8192-pixel frames in batches of 64 would ask for 26 GB.
MAX_BATCH_BYTES = 2**32


@dataclass
class PairIndex:
    """Which frames make each pair, and its target.

    Attributes:
        caches: `.npy` frame caches (N_s, C, S, S) uint8, one per source (sequence / scene).
        source: (P,) index into `caches`.
        first, second: (P,) frame indices of the pair's two images in their cache.
        R: (P, 3, 3) float64 targets C_21 (`rotlearn.geometry.relative_rotation`).
        names: a name per cache (sequence or scene), for messages and reports.
    """

    caches: list[Path]
    source: np.ndarray
    first: np.ndarray
    second: np.ndarray
    R: np.ndarray
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.source)

    def subset(self, keep: np.ndarray) -> PairIndex:
        return PairIndex(
            self.caches, self.source[keep], self.first[keep], self.second[keep], self.R[keep],
            self.names,
        )  # fmt: skip

    @staticmethod
    def concat(parts: list[PairIndex]) -> PairIndex:
        """One index over several, with their caches listed one after the other."""
        offsets = np.cumsum([0] + [len(p.caches) for p in parts])
        return PairIndex(
            caches=[c for p in parts for c in p.caches],
            source=np.concatenate([p.source + o for p, o in zip(parts, offsets, strict=False)]),
            first=np.concatenate([p.first for p in parts]),
            second=np.concatenate([p.second for p in parts]),
            R=np.concatenate([p.R for p in parts]).reshape(-1, 3, 3),
            names=[n for p in parts for n in p.names],
        )


def _file_identity(path: Path) -> tuple[int, ...]:
    """What tells a file from one written in its place: device, inode, size, modification."""
    found = os.stat(path)
    return found.st_dev, found.st_ino, found.st_size, found.st_mtime_ns


class ImagePairs(Dataset):
    """A fixed, ordered set of image pairs; fetched a whole batch at a time.

    Args:
        index: the pairs.
        corrupt_fraction: the last fraction of the pairs is marked `corrupted` and carries
            erasing boxes (one per image: random erasing, the corrupted inputs of the paper's
            OOD experiment, Table I), drawn from `seed`.
        seed: seed of the erasing boxes.
    """

    def __init__(self, index: PairIndex, corrupt_fraction: float = 0.0, seed: int = 0) -> None:
        self.index = index
        self.R = torch.from_numpy(index.R).float()
        self.q = rotmat_to_quat(torch.from_numpy(index.R)).float()
        self.corrupted = corrupted_flags(len(index), corrupt_fraction)
        self._arrays: list[np.ndarray] | None = None
        self._opened: list[tuple[int, ...]] | None = None  # each cache file as first opened
        size = self.arrays[0].shape[-1] if len(index) else 1
        generator = torch.Generator().manual_seed(draw_seed(seed, SPLITS["test"], 7))
        self.boxes = draw_erasing_boxes(2 * len(index), size, size, generator).view(-1, 2, 4)

    @property
    def arrays(self) -> list[np.ndarray]:
        """The memory-mapped caches, opened lazily in each process (loader workers included).

        Raises:
            ValueError: naming a cache that is not the file first opened (a loader worker
                started with `spawn` opens them again: another run may have rebuilt one)."""
        if self._arrays is None:
            arrays = [
                np.load(path, mmap_mode="r", allow_pickle=False) for path in self.index.caches
            ]
            opened = [_file_identity(path) for path in self.index.caches]
            for path, now, then in zip(
                self.index.caches, opened, self._opened or opened, strict=True
            ):
                if now != then:
                    raise ValueError(f"{path}: the frame cache changed after this run read it "
                                     "(rebuilt by another run?); run again")  # fmt: skip
            self._arrays, self._opened = arrays, opened
        return self._arrays

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_arrays": None}

    def __len__(self) -> int:
        return len(self.index)

    def __getitems__(self, indices: list[int]) -> dict[str, Tensor]:
        idx = np.asarray(indices, dtype=np.int64)
        source = self.index.source[idx]
        first_array = self.arrays[int(source[0])]
        channels, size = first_array.shape[1], first_array.shape[-1]
        batch = torch.empty((len(idx), 2 * channels, size, size), dtype=torch.uint8)
        if get_worker_info() is not None:  # filled in place in shared memory: no copy to send
            batch.share_memory_()
        images = batch.numpy()
        for s in np.unique(source):  # one gather per sequence, not per sample
            rows = np.flatnonzero(source == s)
            array, pairs = self.arrays[int(s)], idx[rows]
            images[rows, :channels] = array[self.index.first[pairs]]
            images[rows, channels:] = array[self.index.second[pairs]]
        t = torch.from_numpy(idx)
        return {
            "input": batch,
            "R": self.R[t],
            "q": self.q[t],
            "corrupted": self.corrupted[t],
            "boxes": self.boxes[t],
            "source": torch.from_numpy(source),
            "index": t,
        }

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {k: v[0] for k, v in self.__getitems__([i]).items()}


def _whole_batch(batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """collate_fn for `ImagePairs.__getitems__`, which already returns a batch."""
    return batch


class _Reflagged(Dataset):
    """`pairs` with their `corrupted` flags replaced by `erase` (P,) bool (which to erase)."""

    def __init__(self, pairs: ImagePairs, erase: Tensor) -> None:
        if erase.shape != (len(pairs),):
            raise ValueError(f"erase must have shape ({len(pairs)},), got {tuple(erase.shape)}")
        self.pairs, self.erase = pairs, erase.bool()

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitems__(self, indices: list[int]) -> dict[str, Tensor]:
        batch = self.pairs.__getitems__(indices)
        return {**batch, "corrupted": self.erase[batch["index"]]}


class ImagePairDataModule(pl.LightningDataModule):
    """Base of the image-pair datamodules: subclasses implement `load(split)` -> `PairIndex`.

    Args:
        batch_size: training batch (paper: 32).
        eval_batch_size: validation and test batch (paper: 64).
        num_workers: loader processes gathering cached frames (0: in the main process).
        corrupt_fraction: fraction of the test set, at its end, that is randomly erased
            (the paper corrupts the second half: 0.5, Table I). Flagged `corrupted`.
        val_fraction: the fraction of each training sequence's / scene's frames, at its end,
            held out for validation (`rotlearn.data.splits.hold_out_tail`: a gap of the pair
            distance between them and the training frames, and no frame of a test pair); the
            validation pairs select the best checkpoint, fit the belief's temperature and set
            the OOD thresholds. 0: no validation pairs from the training sequences.
        mean, std: input normalisation after scaling pixels to [0, 1].
        seed: the data seed (shuffling, test/train split where random, erasing boxes,
            augmentation draws).
        swap_pairs: probability that a training pair has its two frames swapped and its target
            inverted (C_12 = C_21^T; q conjugated). Training only.
        photometric: {"brightness": b, "contrast": c}, each in [0, 1): per training pair, the
            same brightness factor in [1 - b, 1 + b] and contrast factor in [1 - c, 1 + c] for
            both frames (`rotlearn.data.augment`). None: off. Training only.
    """

    # What one input is (its size, channels and normalisation): the members of an ensemble,
    # evaluated on one member's data, must agree on these (rotlearn-eval).
    input_keys = ("image_size", "pair_channels", "mean", "std")

    def __init__(
        self,
        batch_size: Annotated[int, Gt(0)] = 32,
        eval_batch_size: Annotated[int, Gt(0)] = 64,
        num_workers: Annotated[int, Ge(0)] = 2,
        corrupt_fraction: Annotated[float, Ge(0), Le(1)] = 0.0,
        val_fraction: Annotated[float, Ge(0), Lt(1)] = 0.1,
        mean: float = 0.0,
        std: Annotated[float, Gt(0)] = 1.0,
        seed: Annotated[int, Ge(0)] = 0,
        swap_pairs: Annotated[float, Ge(0), Le(1)] = 0.0,
        photometric: dict[str, float] | None = None,
    ) -> None:
        super().__init__()
        self.batch_size, self.eval_batch_size = int(batch_size), int(eval_batch_size)
        self.num_workers, self.val_fraction = int(num_workers), float(val_fraction)
        self.corrupt_fraction = float(corrupt_fraction)
        self.mean, self.std, self.seed = float(mean), float(std), int(seed)
        self.swap_pairs = float(swap_pairs)
        self.photometric = augment.check_photometric(photometric)
        self.sets: dict[str, ImagePairs] = {}

    def refuse_oversized_batches(self, channels: int, size: int) -> None:
        """ConfigError on `batch_size` or `eval_batch_size` where a batch of pairs of
        `channels` x `size` x `size` bytes (uint8) would be over `MAX_BATCH_BYTES`; the
        subclasses call it once they know their frame size, before any frame is read."""
        for key in ("batch_size", "eval_batch_size"):
            if (total := getattr(self, key) * channels * size**2) > MAX_BATCH_BYTES:
                raise ConfigError(
                    key,
                    f"{getattr(self, key)} pairs of {channels} x {size} x {size} bytes take "
                    f"{total / 2**30:.3g} GiB, over the {MAX_BATCH_BYTES / 2**30:g} GiB a batch "
                    "may take (MAX_BATCH_BYTES); lower it or image_size",
                )

    def load(self, split: str) -> PairIndex | None:  # pragma: no cover
        """The pairs of "train" or "test", in a fixed order (frame caches built as needed);
        for "val", the pairs of whole sequences / scenes held out for validation, or None."""
        raise NotImplementedError

    def setup(self, stage: str | None = None) -> None:
        """The three splits: test from the test sequences / scenes; validation from the
        training side only (the tail of each training source, `val_fraction`, and whole held-out
        sources where the dataset has them); training from the rest."""
        if self.sets:
            return
        from rotlearn.data.splits import hold_out_tail

        train, test = self.load("train"), self.load("test")
        train, val = hold_out_tail(train, self.val_fraction, exclude=test)
        if not len(train):  # a sampler of no pairs fails later, naming no file or key
            raise ValueError(
                f"data.root {getattr(self, 'root', '?')}: no training pair left once the test "
                "and validation pairs are taken; more frames, or a lower data.val_fraction or "
                "data.test_fraction"
            )
        held_out = self.load("val")
        if held_out is not None and len(held_out):
            val = PairIndex.concat([val, held_out])
        self.sets = {
            "train": ImagePairs(train),
            "val": ImagePairs(val),
            "test": ImagePairs(test, self.corrupt_fraction, self.seed),
        }

    def _loader(
        self, split: str, batch_size: int, shuffle: bool = False, **kwargs: Any
    ) -> DataLoader:
        generator = torch.Generator().manual_seed(draw_seed(self.seed, SPLITS[split]))
        if "batch_sampler" not in kwargs:
            kwargs.update(batch_size=batch_size, shuffle=shuffle)
            kwargs.update(generator=generator if shuffle else None)
        return DataLoader(
            kwargs.pop("dataset", self.sets[split]),
            collate_fn=_whole_batch,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            pin_memory=torch.cuda.is_available(),
            # the platform's own start method, not the process's: a job of hydra/launcher=joblib
            # runs in a loky process, whose default ("loky") cannot start a loader worker
            multiprocessing_context=_PLATFORM_START if self.num_workers > 0 else None,
            **kwargs,
        )

    def train_dataloader(self) -> DataLoader:
        """Shuffled training batches; with their augmentation draws where any is on."""
        dataset = self.sets["train"]
        if self.swap_pairs > 0 or any(self.photometric.values()):
            dataset = augment.AugmentedPairs(dataset, self.swap_pairs, self.photometric, self.seed)
        return self._loader("train", self.batch_size, shuffle=True, dataset=dataset)

    # -- what the OOD evaluation reads (`rotlearn.ood.source.OODDataSource`) -------------------

    def pair_count(self, split: str) -> int:
        """How many pairs "train", "val" or "test" holds."""
        return len(self.sets[split])

    def pair_shape(self) -> tuple[int, int, int]:
        """(2C, S, S): the shape of one stacked pair."""
        return tuple(self.sets["test"].__getitems__([0])["input"].shape[1:])

    def eval_loader(
        self, split: str, indices: Sequence[int] | None = None, erase: Tensor | None = None
    ) -> DataLoader:
        """Unshuffled evaluation batches of `split`'s pairs, as the loader yields them (uint8;
        `finish_batch` makes them what the model sees).

        Args:
            split: "train", "val" or "test".
            indices: which pairs, in this order (None: all, in their fixed order); batches of
                `eval_batch_size` consecutive entries.
            erase: (P,) bool over the split's P pairs: which ones are erased and flagged
                `corrupted` (None: the split's own flags).
        """
        pairs = self.sets[split]
        dataset = pairs if erase is None else _Reflagged(pairs, erase)
        if indices is None:
            return self._loader(split, self.eval_batch_size, dataset=dataset)
        order, size = [int(i) for i in indices], self.eval_batch_size
        batches = [order[i : i + size] for i in range(0, len(order), size)]
        return self._loader(split, size, dataset=dataset, batch_sampler=batches)

    def unseen_pairs(self, split: str) -> Tensor:
        """(P,) bool: which pairs of `split` come from a sequence / scene that no training pair
        comes from (MAV: the indoor and transition scenes)."""
        index = self.sets[split].index
        trained = set(self.sets["train"].index.names)
        unseen = torch.tensor([name not in trained for name in index.names] or [False])
        return unseen[torch.from_numpy(index.source)]

    def noise_batch(self, n: int) -> dict[str, Tensor]:
        """A loader-style batch of `n` pure-noise uint8 pairs (uniform pixels, seeded by the data
        seed), never erased; R is the identity."""
        generator = torch.Generator().manual_seed(self.seed + 99)
        noise = torch.randint(0, 256, (n, *self.pair_shape()), generator=generator,
                              dtype=torch.uint8)  # fmt: skip
        return {
            "input": noise,
            "R": torch.eye(3).expand(n, 3, 3),
            "q": torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(n, 4),
            "corrupted": torch.zeros(n, dtype=torch.bool),
            "boxes": torch.zeros(n, 2, 4, dtype=torch.long),
        }

    def val_dataloader(self) -> DataLoader | list:
        return self._loader("val", self.eval_batch_size) if len(self.sets["val"]) else []

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", self.eval_batch_size)

    def predict_dataloader(self) -> DataLoader:
        return self.test_dataloader()

    def finish_batch(
        self,
        batch: Any,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> Any:
        """A loader batch as the model sees it: on `device`, uint8 pairs swapped where the
        training loader drew "swap" (R transposed, q conjugated), erased where `corrupted`, then
        floats x / 255, jittered where it drew "jitter", normalised (x - mean) / std, in
        `dtype`; R and q in `dtype` too. The draws' keys are removed.

        Args:
            batch: a batch of `ImagePairs` (a batch whose input is not uint8 is only moved).
            device: where to put it; None: where it is.
            dtype: the float dtype; None: that of batch["R"] (float32 from the loader; in a
                Trainer, Lightning's precision plugin has cast it to the model's input dtype).
        """
        if not isinstance(batch, dict):
            return batch
        if device is not None:
            batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        images = batch.get("input")
        if images is None or images.dtype != torch.uint8:
            return batch
        dtype = dtype if dtype is not None else batch["R"].dtype
        batch = dict(batch)
        R, q = batch["R"], batch["q"]
        swap, jitter = batch.pop("swap", None), batch.pop("jitter", None)
        if swap is not None:
            images, R, q = augment.swap_pairs(images, R, q, swap)
        if bool(batch["corrupted"].any()):
            images = erase_boxes(images, batch["boxes"], batch["corrupted"])
        if jitter is None:
            x = self.normalize(images, dtype)
        else:
            x = augment.apply_jitter(
                images.to(dtype).mul_(1.0 / 255.0), jitter, images.shape[1] // 2
            )
            x = x.sub_(self.mean).div_(self.std)
        return {**batch, "input": x, "R": R.to(dtype), "q": q.to(dtype)}

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """`finish_batch` where the transfer put the batch, in its R's dtype."""
        return self.finish_batch(batch)

    def normalize(self, images: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
        """uint8 pixels -> (x / 255 - mean) / std in `dtype`, any shape (one new tensor, scaled
        in place: this runs on every batch)."""
        x = images.to(dtype).mul_(1.0 / (255.0 * self.std))
        return x.sub_(self.mean / self.std) if self.mean else x

    gray = False  # frames decoded as one channel (MAV) or three (KITTI)

    def preprocess(self, image: np.ndarray) -> np.ndarray:  # pragma: no cover
        """A decoded frame -> the cached (S, S[, 3]) uint8 frame."""
        raise NotImplementedError

    def read_pair(self, first: str | Path, second: str | Path) -> Tensor:
        """Two image files -> one normalised (2C, S, S) float32 pair, exactly as in training
        (`rotlearn-predict` reads KITTI/MAV pairs with it)."""
        from rotlearn.data.images import read_image

        frames = []
        for path in (first, second):
            image = read_image(Path(path), self.gray)  # its errors name the file
            try:
                frame = self.preprocess(image)
            except ValueError as exc:  # e.g. a thin frame over the pixel budget once resized
                raise ValueError(f"{path}: {exc}") from None
            frames.append(frame[None] if self.gray else frame.transpose(2, 0, 1))
        return self.normalize(torch.from_numpy(np.concatenate(frames)))
