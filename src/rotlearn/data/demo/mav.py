"""Demo MAV (EuRoC-like) dataset in the layout `rotlearn.data.mav` reads (`rotlearn-make-demo-data`,
tests). `write_mav_demo(out)` writes `<out>/mav/`:

    flea3/data.csv        "#timestamp [ns],filename", then "<t_ns>,<t_ns>.png" per frame (~20 Hz)
    flea3/data/<t_ns>.png 8-bit grayscale frames
    pose/data.csv         "#timestamp [ns], p_RS_R_x [m], ..., q_RS_w [], q_RS_x [], q_RS_y [],
                          q_RS_z []", 200 Hz: position (m) and camera-to-world orientation R_wc
                          as a Hamilton quaternion SCALAR FIRST (w x y z; rotlearn uses x y z w)
    pairs/{outdoor,transition,indoor}.csv   headerless "id1,id2" rows: frames (0-based rows of
                          flea3/data.csv) a few apart (`MAV_PAIR_GAPS`) inside one scene
Frame timestamps are jittered off the pose clock: match them to the nearest pose (within 30 ms).

The images are rendered and the folder written as `rotlearn.data.demo.synth` says: the orientations
are exactly the rotations between the images; the dataset appears only when complete. The outdoor
scene is a photo-textured street (`rotlearn.data.demo.natural.street_panorama`), the indoor one a
darker room (`room_panorama`: plaster and wood, framed pictures, doors, ceiling lights, tiles).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rotlearn.data.demo.synth import (
    camera_matrix,
    euler_quat,
    panorama_width,
    pixel_rays,
    quat_rotmat,
    render,
    staged,
    write_png,
)
from rotlearn.extras import import_extra

cv2 = import_extra("cv2", "the MAV demo writer")

__all__ = ["MAV_PAIR_GAPS", "MAV_POSE_HEADER", "write_demo", "write_mav_demo"]

MAV_POSE_HEADER = (
    "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
    "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
)
_MAV_T0_NS = 1_403_636_580_000_000_000  # an EuRoC-like epoch
_MAV_POSE_NS = 5_000_000  # 200 Hz
_MAV_FRAME_NS = 50_000_000  # 20 Hz nominal, 10 pose periods
_MAV_JITTER_NS = (1_000, 1_500_000)  # |frame time - nominal time|, never 0: off the pose clock
_MAV_SCENES = (("outdoor", 0.45), ("transition", 0.10), ("indoor", 0.45))
# A pair (i, i + g) for each gap g (frames at 20 Hz): 0.2-0.4 s, about 2-6 degrees (mean ~3.5)
# at the trajectory's rates, i.e. a few pixels even at 64 x 64; three pairs per frame.
MAV_PAIR_GAPS = (4, 6, 8)


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
        return euler_quat(yaw, pitch, roll)

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


def _scene_bounds(frames: int, least: int = 2) -> dict[str, tuple[int, int]]:
    """Frame ranges [start, stop) of the scenes, in time order (~45 %, ~10 %, ~45 %; at least
    `least` frames each, so that each has a pair).

    Raises:
        ValueError: `frames` too few for `least` frames in every scene.
    """
    bounds, start = {}, 0
    for k, (name, fraction) in enumerate(_MAV_SCENES):
        last = k == len(_MAV_SCENES) - 1
        stop = frames if last else start + max(least, round(fraction * frames))
        if stop - start < least:
            raise ValueError(
                f"{frames} frames leave the {name} scene {stop - start} frames; each scene needs "
                f"{least} (the largest pair gap + 1): write more frames or smaller gaps"
            )
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
        return render(indoor if blend else outdoor, rays, R_wc)
    views = [render(p, rays, R_wc).astype(np.float32) for p in panoramas]
    return np.rint((1.0 - blend) * views[0] + blend * views[1]).astype(np.uint8)


def _scene_blend(bounds: dict[str, tuple[int, int]], frames: int) -> np.ndarray:
    """(frames,) indoor weight: 0 outdoors, rising linearly through the transition, 1 indoors."""
    start, stop = bounds["transition"]
    blend = np.zeros(frames)
    blend[start:stop] = np.arange(1, stop - start + 1) / (stop - start + 1)
    blend[bounds["indoor"][0] :] = 1.0
    return blend


def write_mav_demo(
    out: str | Path,
    frames: int = 1200,
    width: int = 320,
    height: int = 256,
    seed: int = 0,
    gaps: Sequence[int] = MAV_PAIR_GAPS,
) -> Path:
    """Write a demo MAV (EuRoC-like) dataset (layout in the module docstring); returns `<out>/mav`.

    A camera (`camera_matrix(width, height)`, 80 degrees across; the real flea3 is 640x512)
    turns smoothly through three scenes in time order: ~45 % of the frames "outdoor" (a bright
    photo-textured street), ~10 % "transition" (a cross-fade between the two views), ~45 %
    "indoor" (a darker room of other textures). Each scene's pairs are (i, i + g) for each gap g
    of `gaps` with both frames inside the scene (default 4, 6, 8 frames: mean ~3.5 degrees;
    1200 frames give ~1600 outdoor pairs). Unseen scenes: trained on `outdoor` (the paper's
    and experiment=mav_ood_demo's choice), the indoor and transition pairs view a scene never
    seen in training; the outdoor test pairs (a seeded 10 % of its pairs, chosen by
    `rotlearn.data.mav`) are new pairs of the training scene. Each frame is rendered at its
    own timestamp,
    which lies 1 us to 1.5 ms off the 200 Hz pose clock: the nearest pose is off by < 0.05
    degrees. pose/data.csv quaternions are w x y z (scalar first), camera to world.

    Args:
        out: parent folder.
        frames: number of frames, enough for max(gaps) + 1 in every scene: 4 (max(gaps) + 1)
            always are (36 for the default gaps).
        width, height: image size in pixels.
        seed: content seed; the same seed writes the same files.
        gaps: frame gaps of the pairs (positive integers).
    """
    from rotlearn.data.demo.natural import room_panorama, street_panorama

    gaps = sorted({int(g) for g in gaps})
    if not gaps or gaps[0] < 1:
        raise ValueError(f"gaps must be positive integers, got {gaps}")
    bounds = _scene_bounds(frames, gaps[-1] + 1)
    out = Path(out)
    rngs = [np.random.default_rng([seed, 2, stream]) for stream in range(4)]
    K = camera_matrix(width, height)
    panoramas = [
        cv2.cvtColor(make(rng, panorama_width(K)), cv2.COLOR_BGR2GRAY)
        for make, rng in zip((street_panorama, room_panorama), rngs[:2], strict=True)
    ]
    trajectory = _MavTrajectory(rngs[2])
    pose_ns, frame_ns = _mav_clock(rngs[3], frames)
    with staged(out, "mav", ["mav"]) as stage:
        root = stage / "mav"
        for sub in ("flea3/data", "pose", "pairs"):
            (root / sub).mkdir(parents=True)
        _write_mav_poses(root / "pose" / "data.csv", trajectory, pose_ns)
        rows = "".join(f"{t},{t}.png\n" for t in frame_ns)
        (root / "flea3" / "data.csv").write_text("#timestamp [ns],filename\n" + rows)
        for name, (start, stop) in bounds.items():
            pairs = "".join(f"{i},{i + g}\n" for g in gaps for i in range(start, stop - g))
            (root / "pairs" / f"{name}.csv").write_text(pairs)
        rays = pixel_rays(K, width, height)
        rotations = quat_rotmat(trajectory.quat(_seconds(frame_ns)))
        for t, R_wc, blend in zip(frame_ns, rotations, _scene_blend(bounds, frames), strict=True):
            image = _mav_frame(panoramas, rays, R_wc, blend)
            write_png(root / "flea3" / "data" / f"{t}.png", image)
    return out / "mav"


def write_demo(out: str | Path, seed: int = 0) -> list[Path]:
    """The default-size demo (`rotlearn-make-demo-data`): the roots written."""
    return [write_mav_demo(out, seed=seed)]
