"""Shared synthesis for the demo datasets (`rotlearn.data.demo.<name>`, `rotlearn-make-demo-data`).

- staging: `staged` writes a dataset in a hidden folder beside its final one and renames it into
  place only when complete, so an interrupted run never leaves a partial dataset under the final
  name (an older copy stays until the new one is complete);
- shapes: `airplane_mesh`, a random airplane with no rotational symmetry;
- rotations: float64 numpy wrappers of `rotlearn.geometry` (quaternions x y z w);
- `render`, the pinhole view of a panorama at infinity (an equirectangular texture, drawn by
  `rotlearn.data.demo.natural`) under pure camera rotation, so that the written orientations are
  exactly the rotations between the images (up to the renderer's 1/32-pixel interpolation grid);
- `smooth_series`, a smooth random process for trajectories.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from rotlearn.extras import import_extra
from rotlearn.geometry import quat_multiply, quat_to_rotmat, so3_exp, so3_exp_quat

cv2 = import_extra("cv2", "the demo-data renderer")

__all__ = [
    "DEMO_MARK",
    "HFOV_DEG",
    "airplane_mesh",
    "camera_matrix",
    "euler_quat",
    "exp_rotvec",
    "panorama_width",
    "pixel_rays",
    "quat_rotmat",
    "render",
    "smooth_series",
    "staged",
    "write_png",
]

HFOV_DEG = 80.0  # horizontal field of view of every demo camera

# ---- staging: a dataset appears under its final name only when complete -------------------------


DEMO_MARK = ".rotlearn-demo"  # in every dataset a demo writer made: only those are rewritten


def _replace_dir(new: Path, final: Path) -> None:
    """Rename `new` to `final`; an existing `final` (a demo dataset: `_check_replaceable`) is
    first renamed aside, then removed."""
    if not final.exists():
        os.replace(new, final)
        return
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    shutil.rmtree(old, ignore_errors=True)
    os.replace(final, old)
    os.replace(new, final)
    shutil.rmtree(old)


def _check_replaceable(final: Path) -> None:
    """Refuse to replace `final` unless it is absent or a demo dataset (it holds `DEMO_MARK`):
    whatever else a user keeps there is never deleted."""
    if os.path.lexists(final) and not (final.is_dir() and (final / DEMO_MARK).is_file()):
        raise FileExistsError(
            f"{final} exists and is not a demo dataset rotlearn wrote (no {DEMO_MARK} in it); "
            "nothing was written: move it away or choose another --out"
        )


@contextmanager
def staged(out: Path, label: str, names: Sequence[str]) -> Iterator[Path]:
    """Yield an empty staging folder `<out>/.<label>.tmp-<pid>`; on success mark each
    `<stage>/<name>` (`DEMO_MARK`) and move it to `<out>/<name>`, which must be absent or an
    earlier demo dataset (checked first, before anything is written). The staging folder is
    removed in every case."""
    for name in names:
        _check_replaceable(out / name)
    stage = out / f".{label}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    try:
        yield stage
        for name in names:
            (stage / name / DEMO_MARK).write_text("written by rotlearn-make-demo-data\n")
            _check_replaceable(out / name)  # again: something may have appeared meanwhile
            _replace_dir(stage / name, out / name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


# ---- shapes --------------------------------------------------------------------------------------


def airplane_mesh(rng: np.random.Generator):
    """A random airplane (fuselage, wings, tail and fin of random sizes: no rotational symmetry)
    as a trimesh.Trimesh, x along the fuselage, centred, bounding-box diagonal 1 (ShapeNet's
    "normalized")."""
    trimesh = import_extra("trimesh", "the demo airplane meshes")

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


# ---- rotations (float64 numpy in and out; rotlearn quaternions are x y z w) ----------------------


def exp_rotvec(phi: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3), radians."""
    return so3_exp(torch.from_numpy(phi)).numpy()


def euler_quat(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4), x y z w, of R_y(yaw) R_x(pitch) R_z(roll) (camera axes: y down,
    x right, z forward). Continuous in the angles: no sign flips along a smooth trajectory."""

    def axis_quat(angle: np.ndarray, axis: int) -> torch.Tensor:
        phi = np.zeros((*angle.shape, 3))
        phi[..., axis] = angle
        return so3_exp_quat(torch.from_numpy(phi))

    q = quat_multiply(axis_quat(yaw, 1), quat_multiply(axis_quat(pitch, 0), axis_quat(roll, 2)))
    return q.numpy()


def quat_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4), x y z w."""
    return quat_to_rotmat(torch.from_numpy(q)).numpy()


# ---- rendering -----------------------------------------------------------------------------------


def camera_matrix(width: int, height: int, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    """Pinhole intrinsics K (3, 3) float64: fx = fy = (width / 2) / tan(hfov / 2), principal point
    at the image centre ((width - 1) / 2, (height - 1) / 2) in pixel-centre coordinates."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def panorama_width(K: np.ndarray) -> int:
    """Panorama width matching the camera's resolution at the image centre (2 pi fx pixels),
    rounded to a multiple of 8: no aliasing and no needless detail."""
    return 8 * max(8, round(2 * np.pi * K[0, 0] / 8))


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera rays K^-1 [u, v, 1] (height, width, 3) float64 of every pixel (u, v)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack((u, v, np.ones_like(u)), axis=-1)
    return pixels @ np.linalg.inv(K).T


def render(panorama: np.ndarray, rays: np.ndarray, R_wc: np.ndarray) -> np.ndarray:
    """View of an equirectangular panorama at infinity from a camera with orientation R_wc.

    Args:
        panorama: (Hp, 2 Hp) or (Hp, 2 Hp, C) uint8; column j is longitude 2 pi j / Wp about the
            world y axis (0 along world z), row i is latitude pi ((i + 0.5) / Hp - 0.5) towards
            world +y (down).
        rays: (H, W, 3) camera rays of the pixels (`pixel_rays`).
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


def write_png(path: Path, image: np.ndarray) -> None:
    """cv2.imwrite at zlib level 3 (a little smaller than OpenCV's default 1, still fast)."""
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise OSError(f"could not write {path}")


# ---- trajectories --------------------------------------------------------------------------------


def smooth_series(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """Stationary smooth Gaussian process (n,): white noise convolved with a Gaussian of `sigma`
    samples, scaled to unit variance."""
    half = int(4 * sigma) + 1
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    kernel /= np.sqrt((kernel**2).sum())
    return np.convolve(rng.standard_normal(n + 2 * half), kernel, mode="valid")
