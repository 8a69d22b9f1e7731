"""Shared fixtures: configs composed with Hydra's compose API (no command line, no run dir)."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

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


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """`rotlearn-train <args>` run to its end in `cwd`, output captured."""
    command = [sys.executable, "-m", "rotlearn.train", *args]
    env = {**os.environ, **_CLI_ENV}
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def checkpoint_epoch(path: Path) -> int:
    """The epoch stored in a checkpoint file, or -1 while it is not (fully) there."""
    try:
        return int(torch.load(path, weights_only=True)["epoch"])
    except (OSError, RuntimeError, EOFError, KeyError):
        return -1


def gen(seed: int) -> torch.Generator:
    """A CPU random generator seeded with `seed` (each test draws from its own stream)."""
    return torch.Generator().manual_seed(seed)


def config_options(group: str) -> list[str]:
    """The options of a config group, read from conf/<group>/*.yaml."""
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


@pytest.fixture
def make_cfg(tmp_path: Path) -> Callable[..., DictConfig]:
    """compose(overrides) -> the train config, writing below a fresh temporary directory."""

    def _make(overrides: Sequence[str] = (), run_dir: Path | None = None) -> DictConfig:
        out = run_dir or tmp_path / "run"
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            return compose(config_name="train", overrides=[f"paths.output_dir={out}", *overrides])

    return _make


@pytest.fixture(scope="session")
def demo_data(tmp_path_factory) -> dict[str, Path]:
    """Small demo datasets in the real layouts, written once per test session: "pts" and "mesh"
    (ShapeNet), "kitti" (sequences 00 and 02) and "mav"."""
    from rotlearn.data.kitti_demo import write_kitti_demo
    from rotlearn.data.mav_demo import write_mav_demo
    from rotlearn.data.shapenet_demo import write_shapenet_demo

    out = tmp_path_factory.mktemp("demo")
    roots = write_shapenet_demo(out, num_train=6, num_test=3, points=96)
    roots["kitti"] = write_kitti_demo(out, sequences=("00", "02"), frames=6, width=62, height=19)
    roots["mav"] = write_mav_demo(out, frames=40, width=64, height=52)
    return roots


# Overrides that point each dataset config at the demo copies, small enough for a unit test.
def demo_overrides(demo_data: dict[str, Path], data: str) -> list[str]:
    return {
        "shapenet": [f"data.root={demo_data['pts']}"],
        "kitti": [f"data.root={demo_data['kitti']}", "data.train_sequences=[02]",
                  "data.test_sequences=[00]", "data.image_size=16", "data.num_workers=0"],
        "mav": [f"data.root={demo_data['mav']}", "data.resize=18", "data.image_size=16",
                "data.num_workers=0"],
    }.get(data, [])  # fmt: skip
