"""model.compile: the net and head compiled with torch.compile train, and their checkpoints load
as eager ones (state_dict keys without `_orig_mod.`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

import rotlearn
from rotlearn.cli.train import ConfigError, build, train
from tests.conftest import FAST, point_pairs

ONE_EPOCH = [*FAST, "trainer.max_epochs=1", "logger=none"]


def _trains_and_loads(make_cfg, backend: str, tmp_path: Path) -> dict:
    cfg = make_cfg([*ONE_EPOCH, f"model.compile={backend}"], run_dir=tmp_path / backend)
    metrics = train(cfg)
    assert metrics["global_step"] == 2
    run = Path(cfg.paths.output_dir)
    state = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    assert state and not any("_orig_mod" in key for key in state)
    predictor = rotlearn.load(run)
    R = predictor(point_pairs(3)).R
    assert R.shape == (3, 3, 3) and bool(R.isfinite().all())
    return metrics


def test_a_compiled_run_trains_as_the_eager_one_and_its_checkpoint_loads(make_cfg, tmp_path):
    """aot_eager: dynamo's graph capture and AOT autograd, no C++ compiler needed."""
    compiled = _trains_and_loads(make_cfg, "aot_eager", tmp_path)
    eager = train(make_cfg(ONE_EPOCH, run_dir=tmp_path / "eager"))
    for key in ("train/loss", "val/err_mean", "test/err_mean"):
        assert compiled[key] == pytest.approx(eager[key], rel=1e-4), key


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("gcc") is None and shutil.which("cc") is None, reason="no C++")
def test_model_compile_true_trains_with_inductor(make_cfg, tmp_path):
    _trains_and_loads(make_cfg, "true", tmp_path)


def test_compiling_keeps_the_modules_and_their_parameters(make_cfg):
    model = build(make_cfg([*ONE_EPOCH, "model.compile=aot_eager"]))[0]
    eager = build(make_cfg(ONE_EPOCH))[0]
    assert type(model.net) is type(eager.net)  # compiled in place, not wrapped
    assert list(model.state_dict()) == list(eager.state_dict())


def test_an_empty_backend_name_is_refused(make_cfg):
    with pytest.raises(ConfigError, match=r"model\.compile: should be a valid boolean or should "
                       r"have at least 1 character, got ''"):  # fmt: skip
        build(make_cfg([*ONE_EPOCH, "model.compile=''"]))
