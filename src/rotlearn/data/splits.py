"""Validation splits of image pairs, taken from the training side and never from the test side.

`hold_out_tail(train, fraction, exclude)` splits each source's (sequence's / scene's) training pairs
by time: the frames at the end of the source form its validation region, a gap of at least the
pair distance separates it from the frames that stay for training, and a pair straddling the two
is dropped. So no frame is both trained on and validated on, and no validation frame lies within
a pair distance of a training frame. Validation pairs that share a frame with a test pair
(`exclude`: a frame of the same cache) are dropped too (MAV, whose test pairs are a random part
of the training scene's pairs), so no test pair and no test frame is ever in validation.

Frames are identified by (cache file, frame index): two sources reading the same cache (MAV's
scenes share the flea3 cache) share frames, so a training pair of one source that reads a frame
within the pair distance of another source's validation frames (the larger of the two sources'
distances) is dropped too.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rotlearn.data.pairs import PairIndex

__all__ = ["frame_keys", "hold_out_tail"]

log = logging.getLogger("rotlearn")


def _codes(source: np.ndarray, frames: np.ndarray, caches: list, universe: list) -> np.ndarray:
    """One int64 per frame: its cache's position in `universe` (-1 if absent) and its index."""
    where = {str(Path(c)): i for i, c in enumerate(universe)}
    cache_ids = np.asarray([where.get(str(Path(c)), -1) for c in caches], dtype=np.int64)
    return cache_ids[source] * (1 << 40) + frames.astype(np.int64)


def _frame_codes(index: PairIndex, universe: list) -> np.ndarray:
    """The codes (`_codes`) of every frame a pair of `index` reads."""
    return np.concatenate(
        [_codes(index.source, f, index.caches, universe) for f in (index.first, index.second)]
    )


def frame_keys(index: PairIndex) -> set[tuple[str, int]]:
    """Every (cache path, frame index) that a pair of `index` reads."""
    caches = [str(Path(c)) for c in index.caches]
    return {
        (caches[s], int(f))
        for frames in (index.first, index.second)
        for s, f in zip(index.source.tolist(), frames.tolist(), strict=True)
    }


def hold_out_tail(
    train: PairIndex, fraction: float, exclude: PairIndex | None = None
) -> tuple[PairIndex, PairIndex]:
    """(training pairs, validation pairs) of `train` (module docstring).

    For each source s with frames lo..hi (n = hi - lo + 1) and pair distance g (the largest
    |second - first| of its pairs): its last n_val = max(ceil(fraction n), g + 1) frames are the
    validation region (frames >= cut); the pairs with both frames there are validation pairs, the
    pairs with both frames below cut - g are training pairs, the rest are dropped. A source too
    short to keep one training pair that way (n < n_val + 2 g + 1) stays whole in training.

    Args:
        train: the training pairs.
        fraction: in [0, 1): the fraction of each source's frames held out (0: none).
        exclude: pairs (the test set) whose frames no validation pair may read.

    Returns:
        Two indexes over the same caches (and names) as `train`.
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"fraction must lie in [0, 1), got {fraction}")
    keep_train = np.ones(len(train), dtype=bool)
    keep_val = np.zeros(len(train), dtype=bool)
    if fraction == 0 or len(train) == 0:
        return train, train.subset(keep_val)
    low = np.minimum(train.first, train.second)
    high = np.maximum(train.first, train.second)
    gaps = np.zeros(int(train.source.max()) + 1, dtype=np.int64)  # each source's pair distance
    np.maximum.at(gaps, train.source, high - low)
    for s in np.unique(train.source):
        rows = train.source == s
        lo, hi = int(low[rows].min()), int(high[rows].max())
        n, gap = hi - lo + 1, int(gaps[s])
        n_val = max(math.ceil(fraction * n), gap + 1)
        if n < n_val + 2 * gap + 1:
            name = train.names[s] if s < len(train.names) else str(s)
            log.info("validation: %s has %d frames, too few to hold out %d; training only",
                     name, n, n_val)  # fmt: skip
            continue
        cut = hi + 1 - n_val
        keep_val[rows] = low[rows] >= cut
        keep_train[rows] = high[rows] < cut - gap
    codes = _frame_codes(train, train.caches).reshape(2, -1)  # first frames, second frames
    if exclude is not None and keep_val.any():
        taken = _frame_codes(exclude, train.caches)
        for code in codes:
            keep_val &= ~np.isin(code, taken)
    for s in np.unique(train.source[keep_val]):  # other sources' pairs near its validation
        validated = np.unique(
            np.concatenate([code[keep_val & (train.source == s)] for code in codes])
        )
        reach = np.maximum(gaps[s], gaps[train.source])  # the larger of the two distances
        for code in codes:
            keep_train &= (train.source == s) | ~_within(code, validated, reach)
    return train.subset(keep_train), train.subset(keep_val)


def _within(codes: np.ndarray, targets: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Which `codes` lie within `distance` (one per code) frames of one of `targets` (sorted)
    of their cache."""
    at = np.searchsorted(targets, codes)
    below = targets[np.clip(at - 1, 0, len(targets) - 1)]
    above = targets[np.clip(at, 0, len(targets) - 1)]
    return (np.abs(codes - below) <= distance) | (np.abs(codes - above) <= distance)
