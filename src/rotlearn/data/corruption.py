"""Random erasing of image pairs (paper section VI-C): the corrupted test inputs of the OOD tests.

Each image of a pair gets one axis-aligned box of fill 0 (black, in pixel values, before any
normalisation), with an area fraction in [0.25, 0.5] and an aspect ratio h/w in [0.33, 3], as
torchvision's `RandomErasing(p=1, scale=(0.25, 0.5), ratio=(0.33, 3), value=0)`. The boxes are
drawn once from a seed for a fixed test set (so every run and every device erases the same
pixels) and applied to whole batches at once with `erase_boxes`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["corrupted_flags", "draw_erasing_boxes", "erase_boxes"]


def draw_erasing_boxes(
    count: int,
    height: int,
    width: int,
    generator: torch.Generator,
    area: tuple[float, float] = (0.25, 0.5),
    aspect: tuple[float, float] = (0.33, 3.0),
) -> Tensor:
    """Random erasing boxes, one per image.

    The area fraction a ~ U(area) and the log aspect ratio ~ U(log aspect); where the box would
    not fit in the image, the aspect ratio is clamped to the range that fits, [a H / W, H / (a W)]
    (never empty), instead of torchvision's retries, so every box has its drawn area. Integer
    rounding moves the area fraction by at most 0.5 / min(height, width) beyond `area`.

    Args:
        count: number of boxes.
        height, width: image size in pixels.
        generator: a seeded CPU generator; the boxes are a function of its state only.
        area: range of the erased area fraction (default 0.25 to 0.5, as in the authors' code).
        aspect: range of the box's height / width (default 0.33 to 3, as in the authors' code).

    Returns:
        (count, 4) int64 boxes (top, left, box height, box width).
    """
    a = torch.empty(count, dtype=torch.float64).uniform_(*area, generator=generator)
    log_r = torch.empty(count, dtype=torch.float64).uniform_(
        math.log(aspect[0]), math.log(aspect[1]), generator=generator
    )
    pixels = a * height * width
    # h = sqrt(a H W r) <= H and w = sqrt(a H W / r) <= W  <=>  a H / W <= r <= H / (a W)
    r = log_r.exp().clamp(a * height / width, height / (a * width))
    h = (pixels * r).sqrt().round().clamp(1, height)
    w = (pixels / h).round().clamp(1, width)
    u = torch.rand(count, 2, dtype=torch.float64, generator=generator)
    top = (u[:, 0] * (height - h + 1)).floor()
    left = (u[:, 1] * (width - w + 1)).floor()
    return torch.stack((top, left, h, w), dim=-1).long()


def erase_boxes(images: Tensor, boxes: Tensor, active: Tensor | None = None) -> Tensor:
    """Images with their boxes set to 0, vectorised over the batch.

    Args:
        images: (B, K * C, H, W) pairs (or tuples) of K images with C channels each, stacked on
            the channel axis (KITTI: K = 2, C = 3; MAV: K = 2, C = 1); any dtype and device.
        boxes: (B, K, 4) integer (top, left, height, width), one box per image.
        active: optional (B,) bool; only these samples are erased.

    Returns:
        (B, K * C, H, W), a new tensor; `images` is not modified.
    """
    b, channels, height, width = images.shape
    k = boxes.shape[-2]
    boxes = boxes.to(images.device)
    top, left, h, w = boxes.unbind(-1)  # (B, K) each
    rows = torch.arange(height, device=images.device)
    cols = torch.arange(width, device=images.device)
    in_rows = (rows >= top[..., None]) & (rows < (top + h)[..., None])  # (B, K, H)
    in_cols = (cols >= left[..., None]) & (cols < (left + w)[..., None])  # (B, K, W)
    mask = in_rows[..., :, None] & in_cols[..., None, :]  # (B, K, H, W)
    if active is not None:
        mask = mask & active.to(images.device).view(b, 1, 1, 1)
    mask = mask.repeat_interleave(channels // k, dim=1)
    return images.masked_fill(mask, 0)


def corrupted_flags(count: int, fraction: float) -> Tensor:
    """Which samples of a fixed, ordered test set are corrupted: the last `fraction` of them
    (the paper corrupts the second half). Returns (count,) bool."""
    flags = torch.zeros(count, dtype=torch.bool)
    flags[count - round(count * fraction) :] = True
    return flags
