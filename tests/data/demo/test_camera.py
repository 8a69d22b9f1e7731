"""The demo street camera: exposure that drifts smoothly, noise of the stated size, 8-bit
clipping, and vehicles that cross the view on their own paths."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn.data.demo import camera


def test_exposure_drifts_smoothly_by_the_stated_stops():
    gains = camera.exposure_gains(np.random.default_rng(0), 20000)
    stops = np.log2(gains)
    assert stops.mean() == pytest.approx(camera.EXPOSURE_BIAS, abs=0.1)
    assert stops.std() == pytest.approx(camera.EXPOSURE_STOPS, rel=0.15)
    # smooth: one frame to the next changes the exposure far less than the drift does
    assert np.abs(np.diff(stops)).max() < 0.2 * camera.EXPOSURE_STOPS


def test_expose_adds_read_and_shot_noise_and_clips_to_8_bits():
    rng = np.random.default_rng(1)
    flat = np.full((200, 200, 3), 100, np.uint8)
    out = camera.expose(flat, 1.0, rng)
    assert out.dtype == np.uint8 and out.shape == flat.shape
    expected = np.sqrt(camera.READ_NOISE**2 + camera.SHOT_NOISE * 100)
    assert out.astype(float).mean() == pytest.approx(100, abs=0.2)
    assert out.astype(float).std() == pytest.approx(expected, rel=0.05)
    assert (camera.expose(flat, 4.0, rng) == 255).mean() > 0.99  # over-exposed: saturated
    dark = camera.expose(flat, 0.05, rng).astype(float)  # under-exposed: 5 levels of signal
    assert dark.mean() == pytest.approx(5, abs=0.3)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), width=st.integers(16, 400), height=st.integers(8, 200))
def test_traffic_crosses_the_view_one_vehicle_per_lane_at_a_time(seed, width, height):
    passers = camera.traffic(np.random.default_rng(seed), 300, width, height)
    assert passers
    for p in passers:
        h, w = p.patch.shape[:2]
        assert 1 <= h <= 0.9 * height + 1 and h <= w <= 3 * h + 1 and p.patch.dtype == np.uint8
        assert 15 <= p.end - p.start < 60
        assert width / 310 <= abs(p.speed) <= 10 * width / 310
        assert p.x0 == (-w if p.speed > 0 else width)  # enters from the side it moves away from
    starts = sorted(p.start for p in passers)
    at_once = [sum(p.start <= t < p.end for p in passers) for t in range(300)]
    assert max(at_once) <= camera.LANES and starts[0] < 40


def test_draw_traffic_paints_only_the_vehicles_in_view_where_they_are():
    image = np.zeros((40, 100, 3), np.uint8)
    patch = np.full((10, 20, 3), 200, np.uint8)
    car = camera.Passer(start=5, end=10, x0=-20.0, speed=6.0, top=25, patch=patch)
    assert not camera.draw_traffic(image.copy(), [car], 4).any()  # not yet in view
    painted = camera.draw_traffic(image.copy(), [car], 9)  # x = -20 + 6 * 4 = 4
    expected = image.copy()
    expected[25:35, 4:24] = 200
    np.testing.assert_array_equal(painted, expected)
    half_out = camera.draw_traffic(image.copy(), [car._replace(top=35)], 9)  # clipped at the edge
    assert (half_out[35:40, 4:24] == 200).all() and half_out.sum() == 200 * 5 * 20 * 3
