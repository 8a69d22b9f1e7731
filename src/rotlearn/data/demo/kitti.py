"""Demo KITTI odometry dataset in the layout `rotlearn.data.kitti` reads (`rotlearn-make-demo-data`,
tests). `write_kitti_demo(out)` writes `<out>/kitti/`:

    sequences/<XX>/image_2/<000000>.png   colour frames (6-digit frame index)
    sequences/<XX>/times.txt              one time in seconds per frame ("%e", 0.1 s apart)
    sequences/<XX>/calib.txt              "P0:" .. "P3:", "Tr:" (12 numbers each; P2 = [K | 0])
    poses/<XX>.txt                        12 numbers per frame: row-major 3x4 [R | t], camera to
                                          world (p_w = R p_c + t), the first one the identity
Camera axes as in KITTI: x right, y down, z forward.

The images are rendered and the folder written as `rotlearn.data.demo.synth` says: the orientations
are exactly the rotations between the images; the dataset appears only when complete. The scenes
are photo-textured street panoramas (`rotlearn.data.demo.natural.street_panorama`: real textures,
1/f spectra, occlusion, shading); each sequence views its own scene, so whichever sequence is
tested on shows a street never seen in training, except the revisits (by default sequence 11
drives a new trajectory through sequence 02's street: a seen scene to compare with). Each frame
then goes through a street camera (`rotlearn.data.demo.camera`): drifting exposure, sensor noise
and vehicles crossing the view, so that some pairs are harder than others, as on real streets.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from rotlearn.data.demo import camera
from rotlearn.data.demo.synth import (
    camera_matrix,
    exp_rotvec,
    panorama_width,
    pixel_rays,
    render,
    smooth_series,
    staged,
    write_png,
)

__all__ = [
    "KITTI_REVISITS",
    "KITTI_SCALES",
    "KITTI_SEQUENCES",
    "kitti_scene",
    "write_demo",
    "write_kitti_demo",
]

# The paper's sequences (test on 00, 02 or 05; train on the others), plus 11, a revisit.
KITTI_SEQUENCES = ("00", "02", "05", "06", "07", "08", "09", "10", "11")
# sequence -> the sequence whose street it views (on its own trajectory and starting heading)
KITTI_REVISITS = {"11": "02"}
# `write_demo`'s sizes: the CPU demo, and the paper's scale (experiment=kitti_ood_paper_scale):
# 7 training sequences x 2300 frames ~ 16k training pairs, as the paper's 16.5k (sequences 02,
# 05-10 of KITTI), rendered at the network's 224 x 224 (the paper resizes KITTI's 1241 x 376 to
# it; rendering at that size costs 2.3x less than at half KITTI's and resamples nothing).
KITTI_SCALES = {
    "demo": {"frames": 300, "width": 310, "height": 94},
    "paper": {"frames": 2300, "width": 224, "height": 224},
}


def _kitti_rotvecs(rng: np.random.Generator, steps: int) -> np.ndarray:
    """Per-frame rotation vectors (steps, 3), radians, in the camera frame: yaw (about y) of
    about 1 degree, its sign turning every few tens of frames, smaller pitch (x) and roll (z)."""
    sign = np.tanh(2.5 * smooth_series(rng, steps, 8.0))
    gain = 1.15 + 0.3 * np.tanh(smooth_series(rng, steps, 15.0))
    yaw = gain * sign
    pitch = 0.25 * smooth_series(rng, steps, 3.0)
    roll = 0.15 * smooth_series(rng, steps, 3.0)
    return np.radians(np.stack((pitch, yaw, roll), axis=-1))


def _kitti_poses(rng: np.random.Generator, frames: int) -> np.ndarray:
    """Camera-to-world poses (frames, 3, 4): R_wc(0) = I, R_wc(i + 1) = R_wc(i) Exp(omega_i);
    the camera moves 1 m per frame along its own z axis (invisible: the scene is at infinity)."""
    steps = exp_rotvec(_kitti_rotvecs(rng, frames - 1))
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


def kitti_scene(name: str, revisits: Mapping[str, str] = KITTI_REVISITS) -> str:
    """The sequence whose street `name` views: `revisits[name]` if listed, else `name` itself."""
    return revisits.get(name, name)


def _write_kitti_sequence(
    root: Path,
    name: str,
    scene: str,
    seed: int,
    frames: int,
    K: np.ndarray,
    width: int,
    height: int,
    street_camera: bool,
) -> None:
    """One sequence: poses, times.txt, calib.txt and image_2 frames. The sequence views the
    street panorama of `scene` (a sequence name; drawn from the stream (seed, scene number)),
    from its own starting heading (a roll of the panorama) and with its own motion, exposure and
    traffic (`street_camera`), from separate streams of (seed, sequence number)."""
    from rotlearn.data.demo.natural import street_panorama

    world = street_panorama(np.random.default_rng([seed, 1, 2, int(scene)]), panorama_width(K))
    heading = np.random.default_rng([seed, 1, int(name), 0]).integers(world.shape[1])
    panorama = np.roll(world, heading, axis=1)
    poses = _kitti_poses(np.random.default_rng([seed, 1, int(name), 1]), frames)
    folder = root / "sequences" / name
    (folder / "image_2").mkdir(parents=True)
    (root / "poses").mkdir(exist_ok=True)  # also made before the sequences are written
    np.savetxt(root / "poses" / f"{name}.txt", poses.reshape(frames, 12), fmt="%e")
    np.savetxt(folder / "times.txt", 0.1 * np.arange(frames), fmt="%e")
    (folder / "calib.txt").write_text(_kitti_calib(K))
    rays = pixel_rays(K, width, height)
    if street_camera:  # its own streams: the poses and the renders do not depend on it
        exposure = np.random.default_rng([seed, 1, int(name), 2])
        gains = camera.exposure_gains(exposure, frames)
        traffic = np.random.default_rng([seed, 1, int(name), 3])
        passers = camera.traffic(traffic, frames, width, height)
    for i, pose in enumerate(poses):
        image = render(panorama, rays, pose[:, :3])
        if street_camera:
            image = camera.expose(camera.draw_traffic(image, passers, i), gains[i], exposure)
        write_png(folder / "image_2" / f"{i:06d}.png", image)


def write_kitti_demo(
    out: str | Path,
    sequences: Sequence[str] = KITTI_SEQUENCES,
    frames: int = 300,
    width: int = 310,
    height: int = 94,
    seed: int = 0,
    revisits: Mapping[str, str] = KITTI_REVISITS,
    workers: int = 1,
    street_camera: bool = True,
) -> Path:
    """Write a demo KITTI odometry dataset (layout in the module docstring); returns `<out>/kitti`.

    Scenes (what is seen, for "unseen scene" tests): every sequence views its own street, a
    photo-textured panorama at infinity (`rotlearn.data.demo.natural.street_panorama`) drawn from
    (seed, sequence number), so a test sequence (conf/data/kitti.yaml and experiment=
    kitti_ood_demo test on 00 and train on 02, 05-10) shows a street never seen in training;
    a sequence listed in `revisits` instead views the street of the sequence it maps to, on its
    own trajectory (default: 11 revisits 02, so `data.test_sequences=[11]` tests on new views
    of a training street; 11 is not among the default training sequences). Sequence names must
    be digits; scenes are deterministic in `seed` and do not depend on which sequences are
    written.

    Each sequence starts at its own heading and turns under pure rotation: R_wc(i + 1) = R_wc(i)
    Exp(omega_i), omega_i (camera frame) a smooth random process of about 1 degree per frame (mostly
    0.3-1.5, mean ~1), mostly yaw whose sign turns every few tens of frames, so neither "identity"
    nor "the mean rotation" predicts it. The camera also moves 1 m per frame along its z axis; with
    the scene at infinity this has no visual effect. Intrinsics: `camera_matrix(width, height)` (80
    degrees across), P2 = [K | 0]. Poses are written with "%e" (7 significant digits); the images
    are rendered from the float64 poses they round (orthonormal to ~1e-14), exact up to the
    renderer's 1/32-pixel interpolation grid (~0.01 degrees at 310 pixels across); the street
    camera then changes pixels (exposure, noise, vehicles moving on their own), never a pose.

    Args:
        out: parent folder.
        sequences: two-digit sequence names, e.g. ("00", "01").
        frames: frames per sequence (>= 2).
        width, height: image size in pixels.
        seed: content seed; the same seed writes the same files.
        workers: processes writing sequences side by side (the files do not depend on it).
        street_camera: what a street camera adds to each rendered view
            (`rotlearn.data.demo.camera`): exposure that drifts by about a stop, sensor noise and
            vehicles crossing the view; False writes the exact renders.
    """
    names = [*sequences, *revisits.values()]
    if frames < 2 or not all(str(s).isdigit() for s in names):
        raise ValueError(f"need frames >= 2 and digit sequence names, got {frames}, {sequences}")
    out = Path(out)
    K = camera_matrix(width, height)
    with staged(out, "kitti", ["kitti"]) as stage:
        jobs = [(stage / "kitti", name, kitti_scene(name, revisits), seed, frames, K, width,
                 height, street_camera) for name in sequences]  # fmt: skip
        (stage / "kitti" / "poses").mkdir(parents=True)
        if workers > 1 and len(jobs) > 1:
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(min(workers, len(jobs))) as pool:
                for done in [pool.submit(_write_kitti_sequence, *job) for job in jobs]:
                    done.result()
        else:
            for job in jobs:
                _write_kitti_sequence(*job)
    return out / "kitti"


def write_demo(
    out: str | Path,
    seed: int = 0,
    scale: str = "demo",
    workers: int = 1,
    street_camera: bool = True,
) -> list[Path]:
    """The demo (`rotlearn-make-demo-data`) at one of `KITTI_SCALES`, with or without the street
    camera (`write_kitti_demo`): the roots written."""
    if scale not in KITTI_SCALES:
        raise ValueError(f"scale must be one of {sorted(KITTI_SCALES)}, got {scale!r}")
    sizes = KITTI_SCALES[scale]
    return [write_kitti_demo(out, seed=seed, workers=workers, street_camera=street_camera, **sizes)]
