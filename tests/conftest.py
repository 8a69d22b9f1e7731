"""Shared fixtures: configs composed with Hydra's compose API (no command line, no run dir)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from rotlearn.paths import config_dir

CONFIG_DIR = config_dir()

# A network small enough that a test epoch takes milliseconds.
SMALL_NET = ["net.point_channels=[16,32,64]", "net.head_channels=[32,16]"]


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
    """Small demo datasets in the real layouts, written once per test session."""
    from rotlearn.data.demo import write_shapenet_demo

    return write_shapenet_demo(tmp_path_factory.mktemp("demo"), num_train=6, num_test=3, points=96)
