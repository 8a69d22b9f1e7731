"""Shared fixtures: configs composed with Hydra's compose API (no command line, no run dir)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from omegaconf import DictConfig

from rotlearn.config import compose
from rotlearn.geometry import so3_exp
from rotlearn.paths import config_dir

CONFIG_DIR = config_dir()

# A network small enough that a test epoch takes milliseconds.
SMALL_NET = ["net.point_channels=[16,32,64]", "net.head_channels=[32,16]"]
# A tiny synthetic run on the CPU, no progress bar.
FAST = ["data=tiny", "trainer=cpu", "trainer.enable_progress_bar=false", *SMALL_NET]
# A run long enough to be interrupted between checkpoints (resume and signal tests).
RESUMABLE = [
    "data=tiny",
    "data.batches_per_epoch=25",
    "trainer.max_epochs=6",
    "trainer.enable_progress_bar=false",
    "logger=csv",
    *SMALL_NET,
]
_CLI_ENV = {"HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore"}


def pytest_configure(config: pytest.Config) -> None:
    """One cache of compiled kernels (the A layer's C kernel) for the whole session, shared by
    every test and every subprocess it starts, so the first compile is paid once (at collection:
    test modules ask whether the kernel is available), and the user's ~/.cache is left alone.
    A ROTLEARN_CACHE_DIR set by the caller is kept (a persistent cache across sessions)."""
    if not os.environ.get("ROTLEARN_CACHE_DIR"):
        root = Path(tempfile.mkdtemp(prefix="rotlearn-test-cache-"))
        os.environ["ROTLEARN_CACHE_DIR"] = str(root)
        config.add_cleanup(lambda: shutil.rmtree(root, ignore_errors=True))


def start_cli(args: list[str], cwd: Path) -> subprocess.Popen:
    """`rotlearn-train <args>` in a subprocess in `cwd` (stdout dropped, stderr piped)."""
    return subprocess.Popen(
        [sys.executable, "-m", "rotlearn.train", *args],
        cwd=cwd,
        env={**os.environ, **_CLI_ENV},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def run_cli(
    args: list[str], cwd: Path, umask: int | None = None, warnings: bool = False
) -> subprocess.CompletedProcess:
    """`rotlearn-train <args>` run to its end in `cwd`, output captured; under `umask` if given;
    with Python's default warning filters if `warnings` (else warnings are ignored)."""
    command = [sys.executable, "-m", "rotlearn.train", *args]
    env = {**os.environ, **_CLI_ENV}
    if warnings:
        env.pop("PYTHONWARNINGS", None)
    preexec = (lambda: os.umask(umask)) if umask is not None else None
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600,
        preexec_fn=preexec,
    )  # fmt: skip


def modes(root: Path) -> dict[str, int]:
    """{path relative to `root`: permission bits} of every file and folder below it."""
    return {str(p.relative_to(root)): p.stat().st_mode & 0o777 for p in sorted(root.rglob("*"))}


def tensorboard_events(run_dir: Path) -> dict[str, Any]:
    """The TensorBoard runs below `<run_dir>/tensorboard/`: {relative run path: its loaded
    EventAccumulator} (every kind of event kept)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    root = Path(run_dir) / "tensorboard"
    runs = {}
    for folder in sorted({p.parent for p in root.rglob("events.out.tfevents.*")}):
        sizes = {"scalars": 0, "images": 0, "tensors": 0}
        runs[str(folder.relative_to(root))] = EventAccumulator(str(folder), sizes).Reload()
    return runs


def scalar_tags(run_dir: Path) -> set[str]:
    """Every scalar tag of a run's TensorBoard events: the scalar cards TensorBoard shows."""
    return {tag for events in tensorboard_events(run_dir).values()
            for tag in events.Tags()["scalars"]}  # fmt: skip


def checkpoint_epoch(path: Path) -> int:
    """The epoch stored in a checkpoint file, or -1 while it is not (fully) there."""
    try:
        return int(torch.load(path, weights_only=True)["epoch"])
    except (OSError, RuntimeError, EOFError, KeyError):
        return -1


# -- received runs: one finished run made once per session, copied per test -----------------------

ONE_EPOCH_RUN = ["data=tiny", "trainer=cpu", "trainer.max_epochs=1",
                 "trainer.enable_progress_bar=false", "logger=csv", *SMALL_NET]  # fmt: skip


@pytest.fixture(scope="session")
def finished_run(tmp_path_factory) -> Path:
    """A finished one-epoch run made by `rotlearn-train` (checkpoints best and last, CSV log,
    records, .hydra), once per session; tests copy it (`copy_run`), never change it."""
    cwd = tmp_path_factory.mktemp("finished")
    run = cwd / "run"
    done = run_cli([*ONE_EPOCH_RUN, f"hydra.run.dir={run}"], cwd)
    assert done.returncode == 0, done.stderr
    return run


def copy_run(source: Path, target: Path, resumable: bool = False) -> Path:
    """A copy of a run at `target` (its checkpoints still name the source's folder, as a received
    run's do). `resumable`: as if killed in its second epoch (no metrics.json, status
    INTERRUPTED)."""
    shutil.copytree(source, target, symlinks=True)
    if resumable:
        (target / "metrics.json").unlink()
        (target / "status.json").write_text(json.dumps({"status": "INTERRUPTED"}))
    return target


def model_checkpoint(path: Path, overrides: Sequence[str] = ()) -> Path:
    """A checkpoint at `path` holding the weights of the model the train config with
    `overrides` builds (epoch 0, no training): what a resume checks a run's last.ckpt against."""
    from hydra.utils import instantiate

    cfg = compose(["paths.output_dir=.", *overrides], check=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"epoch": 0, "state_dict": instantiate(cfg.model).state_dict()}, path)
    return path


def tree_hashes(root: Path, skip: Path | None = None) -> dict[str, str]:
    """sha256 of every file below `root` (symlinks as their target's name, folders as "dir"),
    by relative path; `skip` (a folder below `root`) left out."""
    found = {}
    for path in sorted(root.rglob("*")):
        if skip is not None and path.is_relative_to(skip):
            continue
        if path.is_symlink():
            found[str(path.relative_to(root))] = f"-> {os.readlink(path)}"
        elif path.is_file():
            found[str(path.relative_to(root))] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            found[str(path.relative_to(root))] = "dir"
    return found


@contextlib.contextmanager
def unchanged(root: Path) -> Iterator[None]:
    """Assert that the block changed, added and removed nothing below `root` (its tree's
    hashes, `tree_hashes`), also when the block raised (a refusal must lose nothing)."""
    before = tree_hashes(root)
    try:
        yield
    finally:
        assert tree_hashes(root) == before, f"the tree below {root} changed"


def doubling(leaf: Any, levels: int = 40, kind: type = list) -> Any:
    """`leaf` held twice per level, `levels` deep (a list or tuple per level): 2**levels leaves
    as a tree, one object per level in memory and in a pickle (its memo stores each once), a few
    hundred bytes for a hostile file."""
    tree = leaf
    for _ in range(levels):
        tree = kind([tree, tree])
    return tree


@contextlib.contextmanager
def within(seconds: float) -> Iterator[None]:
    """Fail the block with TimeoutError when it takes longer than `seconds` (SIGALRM: also a
    read or an open that would block forever is interrupted)."""

    def expire(signum, frame):
        raise TimeoutError(f"took longer than {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    start = time.monotonic()
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert time.monotonic() - start < seconds


DTYPES = [torch.float32, torch.float64]  # every public function is tested in both
ATOL = {torch.float32: 1e-5, torch.float64: 1e-12}  # per-dtype absolute tolerance of the maths


def gen(seed: int) -> torch.Generator:
    """A CPU random generator seeded with `seed` (each test draws from its own stream)."""
    return torch.Generator().manual_seed(seed)


def randn(seed: int, shape: tuple[int, ...], dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Standard normal draws from `gen(seed)`."""
    return torch.randn(shape, generator=gen(seed), dtype=dtype)


def point_pairs(n: int = 3, seed: int = 0, points: int = 16) -> torch.Tensor:
    """(n, points, 6) pairs of unit vectors (u_i, v_i), as the synthetic training pairs are (a
    predictor rescales other u_i, with an `InputAdjustedWarning`)."""
    x = torch.randn(n, points, 2, 3, generator=gen(seed))
    return (x / torch.linalg.vector_norm(x, dim=-1, keepdim=True)).flatten(-2)


def scipy_rotmats(seed: int, n: int) -> torch.Tensor:
    """Haar-random rotations from scipy (independent of rotlearn), float64."""
    from scipy.spatial.transform import Rotation  # here: the solver's tests run without scipy

    return torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())


def assert_rotation(R: torch.Tensor, atol: float) -> None:
    """R (..., 3, 3) is orthonormal with determinant 1, to `atol`."""
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=atol, rtol=0)
    torch.testing.assert_close(
        torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=atol, rtol=0
    )


def config_options(group: str) -> list[str]:
    """The options of a config group, read from conf/<group>/*.yaml."""
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


@pytest.fixture
def make_cfg(tmp_path: Path) -> Callable[..., DictConfig]:
    """compose(overrides) -> the train config (`rotlearn.config.compose`, not yet validated),
    writing below a fresh temporary directory."""

    def _make(overrides: Sequence[str] = (), run_dir: Path | None = None) -> DictConfig:
        out = run_dir or tmp_path / "run"
        return compose([f"paths.output_dir={out}", *overrides], check=False)

    return _make


@pytest.fixture
def on_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Callable[[DictConfig], DictConfig]:
    """cfg -> cfg, once the (empty) folders and files that its data root must hold exist
    (`rotlearn.config.checks.data_paths`), relative roots inside a fresh working directory:
    enough for a config to validate without its dataset, not to read one."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROTLEARN_DATA_DIR", raising=False)
    return make_data_layout


def make_data_layout(cfg: DictConfig) -> DictConfig:
    """Create (empty) the folders and files that the data root of `cfg` must hold; returns cfg."""
    from omegaconf import OmegaConf

    from rotlearn.config.checks import data_paths

    for _, path in data_paths(OmegaConf.to_container(cfg.data, resolve=True)):
        if path.suffix:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        else:
            path.mkdir(parents=True, exist_ok=True)
    return cfg


@pytest.fixture(scope="session")
def demo_data(tmp_path_factory) -> dict[str, Path]:
    """Small demo datasets in the real layouts, written once per test session: "pts" and "mesh"
    (ShapeNet), "kitti" (sequences 00 and 02) and "mav"."""
    from rotlearn.data.demo.kitti import write_kitti_demo
    from rotlearn.data.demo.mav import write_mav_demo
    from rotlearn.data.demo.shapenet import write_shapenet_demo

    out = tmp_path_factory.mktemp("demo")
    roots = write_shapenet_demo(out, num_train=6, num_test=3, points=96)
    roots["kitti"] = write_kitti_demo(out, sequences=("00", "02"), frames=10, width=62, height=19)
    roots["mav"] = write_mav_demo(out, frames=40, width=64, height=52)
    return roots


# Overrides that point each dataset config (and its `_demo` option) at the test session's demo
# copies, small enough for a unit test.
def demo_overrides(demo_data: dict[str, Path], data: str) -> list[str]:
    return {
        "shapenet": [f"data.root={demo_data['pts']}"],
        "kitti": [f"data.root={demo_data['kitti']}", "data.train_sequences=[02]",
                  "data.test_sequences=[00]", "data.val_sequences=[]", "data.val_fraction=0.1",
                  "data.image_size=16", "data.num_workers=0"],
        "mav": [f"data.root={demo_data['mav']}", "data.resize=18", "data.image_size=16",
                "data.num_workers=0"],
    }.get(data.removesuffix("_demo"), [])  # fmt: skip


# -- small datasets in the real on-disk layouts ---------------------------------------------


def rot_y(deg: float) -> np.ndarray:
    """The rotation by `deg` degrees about y (float64, 3 x 3)."""
    return so3_exp(torch.tensor([0.0, math.radians(deg), 0.0], dtype=torch.float64)).numpy()


def pose_line(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> str:
    return " ".join(f"{v:e}" for v in np.hstack([R, np.asarray(t)[:, None]]).ravel())


def yaw_sequence(n: int, step_deg: float) -> list[np.ndarray]:
    """n camera rotations turning by `step_deg` about y per frame."""
    return [rot_y(step_deg * i) for i in range(n)]


def write_kitti(
    root: Path,
    rotations: dict[str, list[np.ndarray]],
    size: tuple[int, int] = (24, 16),
    seed: int = 0,
    smooth: bool = False,
) -> Path:
    """A KITTI layout: sequences/XX/image_2/NNNNNN.png (random colour; `smooth`: a coarse random
    image resized up, which an auto-encoder can learn) and poses/XX.txt, one camera-to-world
    [R | t] line per frame (t = (0, 0, frame)) for each sequence's rotations."""
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(seed)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    for seq, Rs in rotations.items():
        folder = root / "sequences" / seq / "image_2"
        folder.mkdir(parents=True, exist_ok=True)
        for i in range(len(Rs)):
            if smooth:
                coarse = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)
                image = cv2.resize(coarse, size)
            else:
                image = rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
            cv2.imwrite(str(folder / f"{i:06d}.png"), image)
        lines = [pose_line(R, (0.0, 0.0, float(i))) for i, R in enumerate(Rs)]
        (root / "poses" / f"{seq}.txt").write_text("\n".join(lines) + "\n")
    return root


def write_mav(root: Path, frames: int = 12, pose_gap_after: int | None = None) -> Path:
    """Frames at 20 Hz (jittered), poses at 100 Hz of a steady yaw of 20 deg/s; three scenes."""
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    (root / "flea3" / "data").mkdir(parents=True)
    (root / "pose").mkdir()
    (root / "pairs").mkdir()
    t_frames = (np.arange(frames) * 50e6 + rng.integers(-2e6, 2e6, frames) + 1e9).astype(np.int64)
    rows = ["#timestamp [ns],filename"]
    for t in t_frames:
        cv2.imwrite(
            str(root / "flea3" / "data" / f"{t}.png"), rng.integers(0, 256, (20, 26), np.uint8)
        )
        rows.append(f"{t},{t}.png")
    (root / "flea3" / "data.csv").write_text("\n".join(rows) + "\n")
    t_poses = np.arange(0, frames * 50e6 + 1e9 + 20e6, 10e6).astype(np.int64)
    if pose_gap_after is not None:  # no pose for 100 ms after frame `pose_gap_after`
        t0 = t_frames[pose_gap_after]
        t_poses = t_poses[(t_poses < t0 - 50e6) | (t_poses > t0 + 50e6)]
    rows = ["#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z"]
    for t in t_poses:
        half = math.radians(20.0 * t / 1e9) / 2
        rows.append(f"{t},0,0,0,{math.cos(half):.9f},0,{math.sin(half):.9f},0")
    (root / "pose" / "data.csv").write_text("\n".join(rows) + "\n")
    third = frames // 3
    for scene, (lo, hi) in {"outdoor": (0, third), "transition": (third, 2 * third),
                            "indoor": (2 * third, frames)}.items():  # fmt: skip
        pairs = "\n".join(f"{i},{i + 1}" for i in range(lo, hi - 1))
        (root / "pairs" / f"{scene}.csv").write_text(pairs + "\n")
    return root


def train_tiny_autoencoder(kitti_root: Path, run_dir: Path, image_size: int = 16) -> Path:
    """A 1-epoch auto-encoder run on a tiny KITTI layout (training sequence 01, test 00), as
    `experiment=kitti_autoencoder` trains it: its run directory, for `callbacks.ood.
    autoencoder_ckpt`."""
    from rotlearn.cli.train import train

    cfg = compose([
        f"paths.output_dir={run_dir}", "experiment=kitti_autoencoder",
        f"data.root={kitti_root}",
        "data.train_sequences=[01]", "data.test_sequences=[00]", "data.num_workers=0",
        "data.batch_size=64", f"data.image_size={image_size}", "net.channels=[4,4,4,4]",
        "net.hidden=8", "net.latent=4", "trainer=cpu", "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false", "logger=none",
    ])  # fmt: skip
    train(cfg)
    return run_dir
