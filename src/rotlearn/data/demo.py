"""Small datasets in the real on-disk layouts, for tests and demos (`rotlearn-make-demo-data`).

ShapeNet: random "airplanes" (fuselage, wings, tail fin of random sizes: no rotational symmetry)
written as ShapeNetCore v2 meshes `<out>/shapenet/02691156/<id>/models/model_normalized.obj`
and as the 6D paper's clouds `<out>/shapenet/{train,test}/<id>.pts` ("x y z" lines).

KITTI odometry (`write_kitti_demo`), `<out>/kitti/`:
    sequences/<XX>/image_2/<000000>.png   colour frames (6-digit frame index)
    sequences/<XX>/times.txt              one time in seconds per frame ("%e", 0.1 s apart)
    sequences/<XX>/calib.txt              "P0:" .. "P3:", "Tr:" (12 numbers each; P2 = [K | 0])
    poses/<XX>.txt                        12 numbers per frame: row-major 3x4 [R | t], camera to
                                          world (p_w = R p_c + t), the first one the identity
Camera axes as in KITTI: x right, y down, z forward.

MAV (EuRoC-like, `write_mav_demo`), `<out>/mav/`:
    flea3/data.csv        "#timestamp [ns],filename", then "<t_ns>,<t_ns>.png" per frame (~20 Hz)
    flea3/data/<t_ns>.png 8-bit grayscale frames
    pose/data.csv         "#timestamp [ns], p_RS_R_x [m], ..., q_RS_w [], q_RS_x [], q_RS_y [],
                          q_RS_z []", 200 Hz: position (m) and camera-to-world orientation R_wc
                          as a Hamilton quaternion SCALAR FIRST (w x y z; rotlearn uses x y z w)
    pairs/{outdoor,transition,indoor}.csv   headerless "id1,id2" rows: consecutive frames (0-based
                          rows of flea3/data.csv) inside one scene
Frame timestamps are jittered off the pose clock: match them to the nearest pose (within 30 ms).

Every image is a view of a procedural panorama at infinity (an equirectangular texture) under pure
camera rotation, so the written orientations are exactly the rotations between the images (up to
the renderer's 1/32-pixel interpolation grid).
Each dataset is written in a hidden staging folder beside its final one and renamed into place
only when complete, so an interrupted run never leaves a partial dataset under the final name.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import torch

from rotlearn.data.shapenet import AIRPLANE_SYNSET
from rotlearn.geometry import quat_multiply, quat_to_rotmat, so3_exp, so3_exp_quat

__all__ = ["camera_matrix", "main", "write_kitti_demo", "write_mav_demo", "write_shapenet_demo"]

DATASETS = ("shapenet", "kitti", "mav")
HFOV_DEG = 80.0  # horizontal field of view of every demo camera
MAV_POSE_HEADER = (
    "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
    "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
)
_MAV_T0_NS = 1_403_636_580_000_000_000  # an EuRoC-like epoch
_MAV_POSE_NS = 5_000_000  # 200 Hz
_MAV_FRAME_NS = 50_000_000  # 20 Hz nominal, 10 pose periods
_MAV_JITTER_NS = (1_000, 1_500_000)  # |frame time - nominal time|, never 0: off the pose clock
_MAV_SCENES = (("outdoor", 0.45), ("transition", 0.10), ("indoor", 0.45))


# ---- staging: a dataset appears under its final name only when complete -------------------------


def _replace_dir(new: Path, final: Path) -> None:
    """Rename `new` to `final`; an existing `final` is first renamed aside, then removed."""
    if not final.exists():
        os.replace(new, final)
        return
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    shutil.rmtree(old, ignore_errors=True)
    os.replace(final, old)
    os.replace(new, final)
    shutil.rmtree(old)


@contextmanager
def _staged(out: Path, label: str, names: Sequence[str]) -> Iterator[Path]:
    """Yield an empty staging folder `<out>/.<label>.tmp-<pid>`; on success move each
    `<stage>/<name>` to `<out>/<name>`. The staging folder is removed in every case."""
    stage = out / f".{label}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    try:
        yield stage
        for name in names:
            _replace_dir(stage / name, out / name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


# ---- ShapeNet ------------------------------------------------------------------------------------


def _airplane(rng: np.random.Generator):
    import trimesh

    length, radius = rng.uniform(1.6, 2.2), rng.uniform(0.12, 0.2)
    fuselage = trimesh.creation.cylinder(radius=radius, height=length, sections=24)
    fuselage.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    span, chord = rng.uniform(1.4, 2.2), rng.uniform(0.25, 0.4)
    wings = trimesh.creation.box(extents=[chord, span, 0.04])
    wings.apply_translation([rng.uniform(-0.2, 0.3), 0.0, rng.uniform(-0.05, 0.05)])
    fin = trimesh.creation.box(extents=[0.25, 0.04, rng.uniform(0.3, 0.5)])
    fin.apply_translation([-length / 2 + 0.15, 0.0, radius + 0.15])
    tail = trimesh.creation.box(extents=[0.18, rng.uniform(0.5, 0.8), 0.03])
    tail.apply_translation([-length / 2 + 0.1, 0.0, 0.0])
    mesh = trimesh.util.concatenate([fuselage, wings, fin, tail])
    mesh.apply_translation(-mesh.bounding_box.centroid)
    mesh.apply_scale(1.0 / np.linalg.norm(mesh.extents))  # ShapeNet "normalized": unit diagonal
    return mesh


def write_shapenet_demo(
    out: str | Path, num_train: int = 12, num_test: int = 4, points: int = 512, seed: int = 0
) -> dict[str, Path]:
    """Write the demo ShapeNet in both layouts under one root, `<out>/shapenet` (data.format=mesh
    reads `<root>/02691156/...`, data.format=pts reads `<root>/{train,test}`); returns
    {"mesh": root, "pts": root}.

    The `.pts` files hold 2 * `points` points: the paper's point_fraction 0.5 keeps `points`.
    """
    import trimesh

    out = Path(out)
    names = {"mesh": "shapenet", "pts": "shapenet"}
    rng = np.random.default_rng(seed)
    with _staged(out, "shapenet", ["shapenet"]) as stage:
        for i in range(num_train + num_test):
            model_id = f"demo{seed:02d}{i:04d}"
            mesh = _airplane(rng)
            folder = stage / names["mesh"] / AIRPLANE_SYNSET / model_id / "models"
            folder.mkdir(parents=True, exist_ok=True)
            mesh.export(folder / "model_normalized.obj")
            cloud, _ = trimesh.sample.sample_surface(mesh, 2 * points, seed=seed * 100003 + i)
            split = stage / names["pts"] / ("train" if i < num_train else "test")
            split.mkdir(parents=True, exist_ok=True)
            lines = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in cloud)
            (split / f"{model_id}.pts").write_text(lines + "\n")
    return {key: out / name for key, name in names.items()}


# ---- rotations (float64 numpy in and out; rotlearn quaternions are x y z w) ----------------------


def _exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3), radians."""
    return so3_exp(torch.from_numpy(phi)).numpy()


def _euler_quat(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4), x y z w, of R_y(yaw) R_x(pitch) R_z(roll) (camera axes: y down,
    x right, z forward). Continuous in the angles: no sign flips along a smooth trajectory."""

    def axis_quat(angle: np.ndarray, axis: int) -> torch.Tensor:
        phi = np.zeros((*angle.shape, 3))
        phi[..., axis] = angle
        return so3_exp_quat(torch.from_numpy(phi))

    q = quat_multiply(axis_quat(yaw, 1), quat_multiply(axis_quat(pitch, 0), axis_quat(roll, 2)))
    return q.numpy()


def _quat_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4), x y z w."""
    return quat_to_rotmat(torch.from_numpy(q)).numpy()


# ---- panoramas -----------------------------------------------------------------------------------


def _periodic_noise(rng: np.random.Generator, height: int, width: int, cells: int, channels: int):
    """Smooth unit-variance noise (height, width, channels) float32, `cells` features around the
    horizon, periodic in width (the panorama's longitude wraps without a seam)."""
    cells = max(2, min(cells, width // 3))
    grid = rng.standard_normal((max(2, cells // 2), cells, channels)).astype(np.float32)
    tiled = cv2.resize(np.tile(grid, (1, 3, 1)), (3 * width, height), interpolation=cv2.INTER_CUBIC)
    noise = tiled.reshape(height, 3 * width, channels)[:, width : 2 * width]
    return noise / max(float(noise.std()), 1e-6)


def _octaves(rng: np.random.Generator, shape: tuple[int, int, int], cells: Sequence[int]):
    """Sum of `_periodic_noise` of `shape` (H, W, C) at each feature count in `cells`, the
    amplitude of each proportional to cells ** -0.25 (fine detail nearly as strong as coarse),
    scaled to unit variance."""
    total = np.zeros(shape, np.float32)
    for c in cells:
        total += c**-0.25 * _periodic_noise(rng, shape[0], shape[1], c, shape[2])
    return total / total.std()


def _wrapped(x: int, width: int) -> tuple[int, int, int]:
    """x and its copies one panorama width left and right: a shape drawn at all three shows on
    both sides of the longitude seam."""
    return (x - width, x, x + width)


def _random_shapes(rng: np.random.Generator, canvas: np.ndarray, count: int, palette) -> None:
    """Draw `count` anti-aliased filled circles, filled rectangles and lines, of colours from
    palette(rng) -> BGR tuple, onto `canvas` (H, W, 3) uint8; sizes in degrees of longitude."""
    height, width = canvas.shape[:2]
    unit = width / 360.0  # pixels per degree
    for _ in range(count):
        kind, x, y = rng.integers(3), int(rng.integers(width)), int(rng.integers(height))
        colour = palette(rng)
        if kind == 0:
            radius = max(1, int(unit * rng.uniform(0.5, 6.0)))
            for u in _wrapped(x, width):
                cv2.circle(canvas, (u, y), radius, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            w, h = (max(1, int(unit * s)) for s in rng.uniform(0.5, 8.0, 2))
            for u in _wrapped(x, width):
                cv2.rectangle(canvas, (u, y), (u + w, y + h), colour, -1)
        else:
            dx, dy = (int(unit * s) for s in rng.uniform(-15.0, 15.0, 2))
            thickness = int(rng.integers(1, 4))
            for u in _wrapped(x, width):
                cv2.line(canvas, (u, y), (u + dx, y + dy), colour, thickness, cv2.LINE_AA)


def _outdoor_panorama(rng: np.random.Generator, width: int) -> np.ndarray:
    """Equirectangular BGR uint8 (width // 2, width): a bright sky over a darker green ground
    (horizon at latitude 0), both shaded by multi-scale noise (features from 60 degrees down to
    about 12 pixels) quantised into flat terraces (flat areas keep the PNGs small), under many
    small shapes and lines of random colours."""
    height = width // 2
    shade = _octaves(rng, (height, width, 1), (6, 24, 96, width // 12))
    ground = (np.arange(height) >= height // 2)[:, None, None]
    base = np.where(ground, np.float32([70, 115, 95]), np.float32([210, 175, 140]))
    image = np.clip(base + 15.0 * np.round(40.0 / 15.0 * shade), 0, 255).astype(np.uint8)
    _random_shapes(rng, image, width // 3, lambda r: tuple(int(v) for v in r.integers(0, 256, 3)))
    return image


def _indoor_panorama(rng: np.random.Generator, width: int) -> np.ndarray:
    """Equirectangular BGR uint8 (width // 2, width), darker than outdoors: overlapping flat
    grey-brown walls and panels with sharp edges, thin dark frames, and smooth faint shading."""
    height = width // 2
    unit = width / 360.0  # pixels per degree
    image = np.full((height, width, 3), 35, np.uint8)
    for _ in range(max(8, width // 8)):
        x, y = int(rng.integers(width)), int(rng.integers(height))
        w, h = (int(unit * s) for s in rng.uniform((2.0, 2.0), (25.0, 20.0)))
        colour = tuple(int(v) for v in rng.integers(15, 110) + rng.integers(-10, 10, 3))
        for u in _wrapped(x, width):
            cv2.rectangle(image, (u, y), (u + w, y + h), colour, -1)
    _random_shapes(rng, image, width // 20, lambda r: (int(r.integers(0, 50)),) * 3)
    shading = 6.0 * _periodic_noise(rng, height, width, width // 12, 1)
    return np.clip(image + shading, 0, 255).astype(np.uint8)


# ---- rendering -----------------------------------------------------------------------------------


def camera_matrix(width: int, height: int, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    """Pinhole intrinsics K (3, 3) float64: fx = fy = (width / 2) / tan(hfov / 2), principal point
    at the image centre ((width - 1) / 2, (height - 1) / 2) in pixel-centre coordinates."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def _panorama_width(K: np.ndarray) -> int:
    """Panorama width matching the camera's resolution at the image centre (2 pi fx pixels),
    rounded to a multiple of 8: no aliasing and no needless detail."""
    return 8 * max(8, round(2 * np.pi * K[0, 0] / 8))


def _pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera rays K^-1 [u, v, 1] (height, width, 3) float64 of every pixel (u, v)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack((u, v, np.ones_like(u)), axis=-1)
    return pixels @ np.linalg.inv(K).T


def _render(panorama: np.ndarray, rays: np.ndarray, R_wc: np.ndarray) -> np.ndarray:
    """View of an equirectangular panorama at infinity from a camera with orientation R_wc.

    Args:
        panorama: (Hp, 2 Hp) or (Hp, 2 Hp, C) uint8; column j is longitude 2 pi j / Wp about the
            world y axis (0 along world z), row i is latitude pi ((i + 0.5) / Hp - 0.5) towards
            world +y (down).
        rays: (H, W, 3) camera rays of the pixels (`_pixel_rays`).
        R_wc: (3, 3) camera-to-world rotation.

    Returns:
        (H, W[, C]) uint8: bilinear look-up of each pixel's world ray R_wc K^-1 [u, v, 1]
        (cv2.remap: positions quantised to 1/32 panorama pixel; longitude wraps).
    """
    height, width = panorama.shape[:2]
    d = (rays @ R_wc.T).astype(np.float32)  # float32 trigonometry: ~1e-4 px, twice as fast
    longitude = np.arctan2(d[..., 0], d[..., 2])
    latitude = np.arctan2(d[..., 1], np.hypot(d[..., 0], d[..., 2]))
    map_x = np.mod(longitude * np.float32(width / (2 * np.pi)), np.float32(width))
    map_y = (latitude / np.float32(np.pi) + np.float32(0.5)) * np.float32(height) - np.float32(0.5)
    return cv2.remap(panorama, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _write_png(path: Path, image: np.ndarray) -> None:
    """cv2.imwrite at zlib level 3 (a little smaller than OpenCV's default 1, still fast)."""
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise OSError(f"could not write {path}")


# ---- KITTI odometry ------------------------------------------------------------------------------


def _smooth_series(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """Stationary smooth Gaussian process (n,): white noise convolved with a Gaussian of `sigma`
    samples, scaled to unit variance."""
    half = int(4 * sigma) + 1
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    kernel /= np.sqrt((kernel**2).sum())
    return np.convolve(rng.standard_normal(n + 2 * half), kernel, mode="valid")


def _kitti_rotvecs(rng: np.random.Generator, steps: int) -> np.ndarray:
    """Per-frame rotation vectors (steps, 3), radians, in the camera frame: yaw (about y) of
    about 1 degree, its sign turning every few tens of frames, smaller pitch (x) and roll (z)."""
    sign = np.tanh(2.5 * _smooth_series(rng, steps, 8.0))
    gain = 1.15 + 0.3 * np.tanh(_smooth_series(rng, steps, 15.0))
    yaw = gain * sign
    pitch = 0.25 * _smooth_series(rng, steps, 3.0)
    roll = 0.15 * _smooth_series(rng, steps, 3.0)
    return np.radians(np.stack((pitch, yaw, roll), axis=-1))


def _kitti_poses(rng: np.random.Generator, frames: int) -> np.ndarray:
    """Camera-to-world poses (frames, 3, 4): R_wc(0) = I, R_wc(i + 1) = R_wc(i) Exp(omega_i);
    the camera moves 1 m per frame along its own z axis (invisible: the scene is at infinity)."""
    steps = _exp(_kitti_rotvecs(rng, frames - 1))
    poses = np.zeros((frames, 3, 4))
    poses[0, :, :3] = np.eye(3)
    for i, step in enumerate(steps):
        poses[i + 1, :, :3] = poses[i, :, :3] @ step
        poses[i + 1, :, 3] = poses[i, :, 3] + poses[i + 1, :, 2]
    return poses


def _kitti_calib(K: np.ndarray) -> str:
    """calib.txt: P0 = P2 = [K | 0] (rendered cameras), P1 = P3 = [K | -fx b, 0, 0] with KITTI's
    0.54 m stereo baseline (not rendered), Tr the KITTI velodyne-to-camera axis swap."""
    left = np.hstack((K, np.zeros((3, 1))))
    right = left.copy()
    right[0, 3] = -0.54 * K[0, 0]
    velo = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])
    rows = {"P0": left, "P1": right, "P2": left, "P3": right, "Tr": velo}
    return "".join(f"{k}: {' '.join(f'{v:e}' for v in m.ravel())}\n" for k, m in rows.items())


def _write_kitti_sequence(
    root: Path, name: str, seed: int, frames: int, K: np.ndarray, width: int, height: int
) -> None:
    """One sequence: poses, times.txt, calib.txt and image_2 frames. Every sequence views the
    same world (one panorama from `seed`), like KITTI's drives through one city, each from its
    own starting heading (a roll of the panorama) and with its own motion, from separate streams
    of (seed, sequence number)."""
    world = _outdoor_panorama(np.random.default_rng([seed, 1, 0]), _panorama_width(K))
    heading = np.random.default_rng([seed, 1, int(name), 0]).integers(world.shape[1])
    panorama = np.roll(world, heading, axis=1)
    poses = _kitti_poses(np.random.default_rng([seed, 1, int(name), 1]), frames)
    folder = root / "sequences" / name
    (folder / "image_2").mkdir(parents=True)
    (root / "poses").mkdir(exist_ok=True)
    np.savetxt(root / "poses" / f"{name}.txt", poses.reshape(frames, 12), fmt="%e")
    np.savetxt(folder / "times.txt", 0.1 * np.arange(frames), fmt="%e")
    (folder / "calib.txt").write_text(_kitti_calib(K))
    rays = _pixel_rays(K, width, height)
    for i, pose in enumerate(poses):
        _write_png(folder / "image_2" / f"{i:06d}.png", _render(panorama, rays, pose[:, :3]))


def write_kitti_demo(
    out: str | Path,
    sequences: Sequence[str] = ("00", "02", "05", "06", "07", "08", "09", "10"),
    frames: int = 300,
    width: int = 310,
    height: int = 94,
    seed: int = 0,
) -> Path:
    """Write a demo KITTI odometry dataset (layout in the module docstring); returns `<out>/kitti`.

    Every sequence views one procedural panorama at infinity (drawn from `seed`), from its own
    starting heading, under pure rotation: R_wc(i + 1) = R_wc(i) Exp(omega_i), omega_i (camera
    frame) a smooth random process of about 1 degree per frame (mostly 0.3-1.5, mean ~1), mostly
    yaw whose sign turns every few tens of frames, so neither "identity" nor "the mean rotation"
    predicts it. The camera also moves 1 m per frame along its z axis; with the scene at infinity
    this has no visual effect. Intrinsics: `camera_matrix(width, height)` (80 degrees across),
    P2 = [K | 0]. Poses are written with "%e" (7 significant digits); the images are rendered
    from the float64 poses they round (orthonormal to ~1e-14), exact up to the renderer's
    1/32-pixel interpolation grid (~0.01 degrees at 310 pixels across).

    Args:
        out: parent folder.
        sequences: two-digit sequence names, e.g. ("00", "01").
        frames: frames per sequence (>= 2).
        width, height: image size in pixels.
        seed: content seed; the same seed writes the same files.
    """
    if frames < 2 or not all(s.isdigit() for s in sequences):
        raise ValueError(f"need frames >= 2 and digit sequence names, got {frames}, {sequences}")
    out = Path(out)
    K = camera_matrix(width, height)
    with _staged(out, "kitti", ["kitti"]) as stage:
        for name in sequences:
            _write_kitti_sequence(stage / "kitti", name, seed, frames, K, width, height)
    return out / "kitti"


# ---- MAV (EuRoC-like) ----------------------------------------------------------------------------


class _MavTrajectory:
    """A smooth camera trajectory, an exact function of time t (seconds): orientation
    R_wc(t) = R_y(yaw) R_x(pitch) R_z(roll), each angle a sum of random sinusoids (angular rate
    mostly 10-20 deg/s, below ~30), and a position drifting round a slow loop."""

    # per angle: amplitudes in degrees (each scaled by a draw in [0.7, 1.3]), frequency range Hz
    _ANGLES = (
        ((40.0, 12.0, 3.0), (0.04, 0.15)),
        ((6.0, 3.0), (0.05, 0.2)),
        ((4.0, 2.0), (0.05, 0.2)),
    )

    def __init__(self, rng: np.random.Generator):
        self._waves = []  # (amplitude rad, frequency Hz, phase rad) arrays per angle
        for amplitudes, hz in self._ANGLES:
            n = len(amplitudes)
            a = np.radians(np.asarray(amplitudes)) * rng.uniform(0.7, 1.3, n)
            self._waves.append((a, rng.uniform(*hz, n), rng.uniform(0, 2 * np.pi, n)))
        self._loop_phase = rng.uniform(0, 2 * np.pi)

    def quat(self, t: np.ndarray) -> np.ndarray:
        """(len(t), 4) unit quaternions of R_wc, x y z w, continuous in t."""
        yaw, pitch, roll = (
            (a * np.sin(2 * np.pi * f * t[:, None] + phase)).sum(-1) for a, f, phase in self._waves
        )
        return _euler_quat(yaw, pitch, roll)

    def position(self, t: np.ndarray) -> np.ndarray:
        """(len(t), 3) camera positions in the world, metres (a 40 s loop)."""
        w = 2 * np.pi * t / 40.0 + self._loop_phase
        return np.stack((2.0 * np.cos(w), 0.3 * np.sin(2 * w), 1.5 * np.sin(w)), axis=-1)


def _mav_clock(rng: np.random.Generator, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer nanosecond timestamps (pose_times (P,), frame_times (frames,)): poses every 5 ms
    from 0.5 s before the first frame to 0.5 s after the last; frames every 50 ms, each off its
    nominal time (a pose time) by 1 us to 1.5 ms either way."""
    nominal = _MAV_T0_NS + 100 * _MAV_POSE_NS + _MAV_FRAME_NS * np.arange(frames, dtype=np.int64)
    jitter = rng.integers(*_MAV_JITTER_NS, frames, endpoint=True) * rng.choice([-1, 1], frames)
    last = nominal[-1] + 100 * _MAV_POSE_NS
    poses = np.arange(_MAV_T0_NS, last + 1, _MAV_POSE_NS, dtype=np.int64)
    return poses, nominal + jitter


def _seconds(t_ns: np.ndarray) -> np.ndarray:
    """Seconds (float64) since the pose clock's start, of integer nanosecond timestamps."""
    return (t_ns - _MAV_T0_NS).astype(np.float64) * 1e-9


def _scene_bounds(frames: int) -> dict[str, tuple[int, int]]:
    """Frame ranges [start, stop) of the scenes, in time order (~45 %, ~10 %, ~45 %; at least
    2 frames each, so each has a pair)."""
    bounds, start = {}, 0
    for k, (name, fraction) in enumerate(_MAV_SCENES):
        last = k == len(_MAV_SCENES) - 1
        stop = frames if last else start + max(2, round(fraction * frames))
        bounds[name], start = (start, stop), stop
    return bounds


def _write_mav_poses(path: Path, trajectory: _MavTrajectory, t_ns: np.ndarray) -> None:
    """pose/data.csv: t_ns, position, quaternion w x y z (%.9f)."""
    t = _seconds(t_ns)
    q = trajectory.quat(t)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    values = np.hstack((trajectory.position(t), q[:, [3, 0, 1, 2]]))
    rows = [
        f"{s}," + ",".join(f"{v:.9f}" for v in row) for s, row in zip(t_ns, values, strict=True)
    ]
    path.write_text(MAV_POSE_HEADER + "\n" + "\n".join(rows) + "\n")


def _mav_frame(panoramas, rays, R_wc: np.ndarray, blend: float) -> np.ndarray:
    """Gray frame: the outdoor view cross-faded to the indoor view by `blend` in [0, 1]."""
    outdoor, indoor = panoramas
    if blend in (0.0, 1.0):
        return _render(indoor if blend else outdoor, rays, R_wc)
    views = [_render(p, rays, R_wc).astype(np.float32) for p in panoramas]
    return np.rint((1.0 - blend) * views[0] + blend * views[1]).astype(np.uint8)


def _scene_blend(frames: int) -> np.ndarray:
    """(frames,) indoor weight: 0 outdoors, rising linearly through the transition, 1 indoors."""
    bounds = _scene_bounds(frames)
    start, stop = bounds["transition"]
    blend = np.zeros(frames)
    blend[start:stop] = np.arange(1, stop - start + 1) / (stop - start + 1)
    blend[bounds["indoor"][0] :] = 1.0
    return blend


def write_mav_demo(
    out: str | Path, frames: int = 600, width: int = 320, height: int = 256, seed: int = 0
) -> Path:
    """Write a demo MAV (EuRoC-like) dataset (layout in the module docstring); returns `<out>/mav`.

    A camera (`camera_matrix(width, height)`, 80 degrees across; the real flea3 is 640x512)
    turns smoothly through three scenes in time order: ~45 % of the frames "outdoor" (a bright,
    busy panorama), ~10 % "transition" (a cross-fade between the two views), ~45 % "indoor" (a
    darker panorama of flat panels and edges). Each frame is rendered at its own timestamp,
    which lies 1 us to 1.5 ms off the 200 Hz pose clock: the nearest pose is off by < 0.05
    degrees. pose/data.csv quaternions are w x y z (scalar first), camera to world.

    Args:
        out: parent folder.
        frames: number of frames (>= 10, so that every scene has a pair).
        width, height: image size in pixels.
        seed: content seed; the same seed writes the same files.
    """
    if frames < 10:
        raise ValueError(f"need frames >= 10, got {frames}")
    out = Path(out)
    rngs = [np.random.default_rng([seed, 2, stream]) for stream in range(4)]
    K = camera_matrix(width, height)
    panoramas = [
        cv2.cvtColor(make(rng, _panorama_width(K)), cv2.COLOR_BGR2GRAY)
        for make, rng in zip((_outdoor_panorama, _indoor_panorama), rngs[:2], strict=True)
    ]
    trajectory = _MavTrajectory(rngs[2])
    pose_ns, frame_ns = _mav_clock(rngs[3], frames)
    with _staged(out, "mav", ["mav"]) as stage:
        root = stage / "mav"
        for sub in ("flea3/data", "pose", "pairs"):
            (root / sub).mkdir(parents=True)
        _write_mav_poses(root / "pose" / "data.csv", trajectory, pose_ns)
        rows = "".join(f"{t},{t}.png\n" for t in frame_ns)
        (root / "flea3" / "data.csv").write_text("#timestamp [ns],filename\n" + rows)
        for name, (start, stop) in _scene_bounds(frames).items():
            pairs = "".join(f"{i},{i + 1}\n" for i in range(start, stop - 1))
            (root / "pairs" / f"{name}.csv").write_text(pairs)
        rays = _pixel_rays(K, width, height)
        rotations = _quat_rotmat(trajectory.quat(_seconds(frame_ns)))
        for t, R_wc, blend in zip(frame_ns, rotations, _scene_blend(frames), strict=True):
            image = _mav_frame(panoramas, rays, R_wc, blend)
            _write_png(root / "flea3" / "data" / f"{t}.png", image)
    return out / "mav"


# ---- command line --------------------------------------------------------------------------------


def _dataset_list(text: str) -> list[str]:
    """--only: comma-separated names from DATASETS."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = sorted(set(names) - set(DATASETS))
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"choose from {', '.join(DATASETS)}; got {text!r}")
    return names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rotlearn-make-demo-data",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default="data/demo", help="where to write (default data/demo)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--only",
        type=_dataset_list,
        default=list(DATASETS),
        help=f"comma-separated subset of {','.join(DATASETS)} (default: all)",
    )
    args = parser.parse_args(argv)
    writers = {
        "shapenet": lambda: sorted(set(write_shapenet_demo(args.out, seed=args.seed).values())),
        "kitti": lambda: [write_kitti_demo(args.out, seed=args.seed)],
        "mav": lambda: [write_mav_demo(args.out, seed=args.seed)],
    }
    for name in (n for n in DATASETS if n in args.only):
        start = time.perf_counter()
        roots = writers[name]()
        seconds = time.perf_counter() - start
        print(f"{name}: {', '.join(map(str, roots))} ({seconds:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
