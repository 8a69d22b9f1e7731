"""What a street camera adds to a rendered view: exposure, sensor noise and passing traffic.

A view rendered by `rotlearn.data.demo.synth.render` is exact and equally easy everywhere: a
panorama at infinity, seen under pure rotation, always fully lit. Real street frames are not.
The auto-exposure lags behind the light (a frame under trees comes out dark, one facing a
sunlit wall bright and clipped), dark frames are noisy, and vehicles cross the view on their
own paths, so part of a pair does not move with the camera. Without these, every clean demo pair
is as hard as every other: the errors of a trained head are homoscedastic (issue 25 measured
Spearman(DT, error) of -0.17 to 0.20 on the clean test street), and a belief has nothing to learn
about when to be unsure. This module adds them, each drawn from the caller's numpy Generator:

- `exposure_gains`: a per-frame gain, a smooth random process in stops;
- `expose`: the gain, then read and shot noise, rounded and clipped to 8 bits;
- `traffic` and `draw_traffic`: textured boxes (crops of the bundled photographs) that enter
  the view, cross it at their own speed in image coordinates and leave, on two lanes.

The poses stay exact: these effects change pixels, never the camera's rotation.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rotlearn.data.demo.synth import smooth_series

__all__ = ["Passer", "draw_traffic", "expose", "exposure_gains", "traffic"]

EXPOSURE_STOPS = 0.8  # standard deviation of the exposure error, in stops (a factor of 2 each)
EXPOSURE_BIAS = -0.3  # its mean, in stops: street frames err towards dark more often than bright
EXPOSURE_FRAMES = 25.0  # how many frames the exposure error takes to change (smoothing sigma)
READ_NOISE = 2.0  # sensor read noise, in 8-bit levels
SHOT_NOISE = 0.5  # shot noise variance per 8-bit level of signal
LANES = 2  # traffic lanes, each with one vehicle at a time at most


class Passer(NamedTuple):
    """A vehicle crossing the view: in frames [start, end), its patch (h, w, 3) uint8 BGR has its
    top-left corner at column `x0 + speed * (frame - start)` and row `top`."""

    start: int
    end: int
    x0: float
    speed: float  # pixels per frame, either way
    top: int
    patch: np.ndarray


def exposure_gains(rng: np.random.Generator, frames: int) -> np.ndarray:
    """(frames,) float64 exposure gains, 2 ** (a smooth Gaussian process of `EXPOSURE_STOPS`
    standard deviation about `EXPOSURE_BIAS`, changing over `EXPOSURE_FRAMES` frames)."""
    stops = EXPOSURE_STOPS * smooth_series(rng, frames, EXPOSURE_FRAMES) + EXPOSURE_BIAS
    return 2.0**stops


def expose(image: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
    """`image` (any shape, uint8) times `gain`, plus Gaussian noise of variance `READ_NOISE`^2 +
    `SHOT_NOISE` x signal, rounded and clipped to uint8 (bright areas saturate, dark ones lose
    their contrast to the noise)."""
    signal = image.astype(np.float32) * np.float32(gain)
    sigma = np.sqrt(np.float32(READ_NOISE**2) + np.float32(SHOT_NOISE) * signal)
    noisy = signal + sigma * rng.standard_normal(image.shape, dtype=np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def traffic(rng: np.random.Generator, frames: int, width: int, height: int) -> list[Passer]:
    """The vehicles that cross a sequence of `frames` views of `width` x `height` pixels: on each
    of `LANES` lanes one after another, each in view for 15-60 frames with 10-80 frames between
    them; a vehicle is 0.3-0.9 of the image height tall and 1-3 times as wide, at 30-120 % of the
    photograph's brightness, and moves 1-10 pixels a frame at 310 pixels across (the demo's
    width; scaled with it), entering from either side."""
    from rotlearn.data.demo.natural import PHOTOS, bundled_images, crop

    photos = [bundled_images()[name] for name in PHOTOS]
    found = []
    for _ in range(LANES):
        start = int(rng.integers(0, 40))
        while start < frames:
            end = start + int(rng.integers(15, 60))
            h = max(1, int(height * rng.uniform(0.3, 0.9)))
            w = max(1, int(h * rng.uniform(1.0, 3.0)))
            photo = photos[int(rng.integers(len(photos)))]
            patch = crop(rng, photo, h, w, rng.uniform(0.5, 2.0)) * rng.uniform(0.3, 1.2)
            speed = rng.uniform(1, 10) * rng.choice([-1.0, 1.0]) * width / 310
            top = int(height * rng.uniform(0.3, 0.7))
            x0 = -w if speed > 0 else width
            patch = np.clip(255 * patch, 0, 255).astype(np.uint8)
            found.append(Passer(start, end, float(x0), float(speed), top, patch))
            start = end + int(rng.integers(10, 80))
    return found


def draw_traffic(image: np.ndarray, passers: list[Passer], frame: int) -> np.ndarray:
    """`image` (H, W, 3) uint8 with the passers in view at `frame` painted over it (in place;
    clipped at the image's edges); returns it."""
    height, width = image.shape[:2]
    for p in (p for p in passers if p.start <= frame < p.end):
        x, y = round(p.x0 + p.speed * (frame - p.start)), p.top
        h, w = p.patch.shape[:2]
        x0, x1, y0, y1 = max(x, 0), min(x + w, width), max(y, 0), min(y + h, height)
        if x1 > x0 and y1 > y0:
            image[y0:y1, x0:x1] = p.patch[y0 - y : y1 - y, x0 - x : x1 - x]
    return image
