"""Photo-textured demo panoramas (rotlearn.data.demo.natural): natural-image statistics (a
1/f^2-like power spectrum, few flat regions), seamless longitude, determinism, bundled images
only."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from rotlearn.data.demo import natural
from rotlearn.data.demo.natural import pink_noise, room_panorama, street_panorama

WIDTH = 512  # panorama width: 1.4 pixels per degree


def spectrum_slope(gray: np.ndarray) -> float:
    """Slope of log power against log frequency of the radially averaged power spectrum of a
    Hann-windowed image, between 4 cycles per image and 0.4 cycles per pixel (natural images:
    about -2)."""
    g = gray.astype(np.float64) - gray.mean()
    h, w = g.shape
    power = np.abs(np.fft.fft2(g * np.hanning(h)[:, None] * np.hanning(w)[None, :])) ** 2
    f = np.hypot(np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]).ravel()
    edges = np.geomspace(4 / min(h, w), 0.4, 16)
    ring = np.digitize(f, edges)
    mean_power = [power.ravel()[ring == k].mean() for k in range(1, len(edges))]
    centres = np.sqrt(edges[1:] * edges[:-1])
    return float(np.polyfit(np.log(centres), np.log(mean_power), 1)[0])


def flat_fraction(gray: np.ndarray) -> float:
    """Fraction of pixels whose 5 x 5 neighbourhood varies by less than one grey level (std)."""
    g = gray.astype(np.float32)
    mean = cv2.blur(g, (5, 5))
    return float(((cv2.blur(g * g, (5, 5)) - mean * mean) < 1.0).mean())


def visible_band(panorama: np.ndarray) -> np.ndarray:
    """Gray rows within 30 degrees of the horizon (what the demo cameras see)."""
    gray = cv2.cvtColor(panorama, cv2.COLOR_BGR2GRAY)
    h = gray.shape[0]
    return gray[h // 2 - h // 6 : h // 2 + h // 6]


@pytest.fixture(scope="module", params=[street_panorama, room_panorama], ids=["street", "room"])
def panorama(request) -> np.ndarray:
    return request.param(np.random.default_rng(0), WIDTH)


def test_panoramas_have_natural_power_spectra_and_few_flat_regions(panorama):
    assert panorama.shape == (WIDTH // 2, WIDTH, 3) and panorama.dtype == np.uint8
    band = visible_band(panorama)
    assert -3.0 < spectrum_slope(band) < -1.5
    assert flat_fraction(band) < 0.2


def test_the_spectrum_slope_tells_white_noise_and_flat_shapes_from_natural_images():
    """The statistics test above can fail: white noise is far too flat a spectrum, an image of
    a few flat rectangles is mostly flat regions."""
    rng = np.random.default_rng(0)
    assert spectrum_slope(rng.integers(0, 256, (128, 512)).astype(np.uint8)) > -0.5
    shapes = np.full((128, 512), 90, np.uint8)
    for _ in range(12):
        x, y = rng.integers(0, 512), rng.integers(0, 128)
        cv2.rectangle(
            shapes, (int(x), int(y)), (int(x) + 40, int(y) + 20), int(rng.integers(256)), -1
        )
    assert flat_fraction(shapes) > 0.5


def test_panoramas_wrap_round_the_longitude_without_a_seam(panorama):
    band = visible_band(panorama).astype(np.float64)
    seam = np.abs(band[:, 0] - band[:, -1]).mean()
    neighbours = np.abs(np.diff(band, axis=1)).mean()
    assert seam < 3 * neighbours


def test_the_room_is_darker_than_the_street():
    street = visible_band(street_panorama(np.random.default_rng(1), WIDTH))
    room = visible_band(room_panorama(np.random.default_rng(1), WIDTH))
    assert room.mean() < street.mean() - 20


@pytest.mark.parametrize("make", [street_panorama, room_panorama])
def test_panoramas_are_deterministic_in_the_generator(make):
    first = make(np.random.default_rng([3, 1]), 256)
    np.testing.assert_array_equal(first, make(np.random.default_rng([3, 1]), 256))
    assert not np.array_equal(first, make(np.random.default_rng([3, 2]), 256))


def test_pink_noise_is_periodic_unit_variance_with_the_asked_slope():
    noise = pink_noise(np.random.default_rng(0), 128, 256, 2.0)
    assert noise.shape == (128, 256) and noise.dtype == np.float32
    assert noise.std() == pytest.approx(1.0, rel=1e-4) and abs(noise.mean()) < 1e-4
    assert spectrum_slope(noise) == pytest.approx(-2.0, abs=0.35)


def test_the_textures_tile_without_seams():
    for name in natural.TEXTURES:
        texture = natural.bundled_images()[name]
        across = np.abs(texture[:, 0] - texture[:, -1]).mean()
        inside = np.abs(np.diff(texture, axis=1)).mean()
        assert across < 1.5 * inside, name


def test_only_files_bundled_in_the_scikit_image_wheel_are_read():
    import skimage.data

    folder = Path(skimage.data.__file__).parent
    for name in natural.TEXTURES + natural.PHOTOS:
        assert (folder / name).is_file(), name


def test_missing_scikit_image_says_how_to_install_it(monkeypatch):
    natural.bundled_images.cache_clear()
    monkeypatch.setitem(sys.modules, "skimage", None)
    monkeypatch.setitem(sys.modules, "skimage.data", None)
    try:
        with pytest.raises(ModuleNotFoundError, match=r"pip install rotlearn\[data\]"):
            street_panorama(np.random.default_rng(0), 64)
    finally:
        natural.bundled_images.cache_clear()
