"""The auto-encoder OOD baseline (paper VI-C.1): shapes, first-image loss, training, loading."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch import nn

import rotlearn
from rotlearn.checkpoint import load_run
from rotlearn.cli.evaluate import evaluation_config
from rotlearn.cli.train import ConfigError, build, train
from rotlearn.lit import AutoEncoderModule, load_autoencoder
from rotlearn.nets import ConvAutoEncoder
from tests.conftest import SMALL_NET, write_kitti

TINY_NET = ["data.image_size=16", "net.channels=[8,8,8,8]", "net.hidden=16", "net.latent=4"]


def tiny_autoencoder(pair_channels: int = 6, image_size: int = 16) -> ConvAutoEncoder:
    return ConvAutoEncoder(pair_channels, image_size, channels=[4, 8, 8], hidden=8, latent=4)


# -- the net ------------------------------------------------------------------------------------


@pytest.mark.parametrize("pair_channels", [6, 2])
@pytest.mark.parametrize(
    ("image_size", "channels"), [(224, [4, 4, 4, 4, 4, 4, 4]), (64, [4, 8, 8]), (50, [4, 8, 8, 8])]
)
def test_decoder_restores_the_exact_image_size(pair_channels, image_size, channels):
    net = ConvAutoEncoder(pair_channels, image_size, channels=channels, hidden=8, latent=4)
    c = pair_channels // 2
    images = torch.randn(2, c, image_size, image_size)
    assert net.encode(images).shape == (2, 4)
    assert net(images).shape == (2, c, image_size, image_size)
    pairs = torch.randn(2, pair_channels, image_size, image_size)
    assert torch.equal(net.first_image(pairs), pairs[:, :c])


def test_paper_sizes_and_a_plain_last_layer():
    """Paper: 224 -> 2 pixels, 1024 x 2 x 2 = 4096 -> 128 -> 16; back 2 -> 4 -> 7 -> ... -> 224."""
    net = ConvAutoEncoder(channels=[4, 4, 4, 4, 4, 4, 1024])  # the paper's sizes, narrower convs
    linears = [m for m in net.encoder.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(4096, 128), (128, 16)]
    deconvs = [m for m in net.decoder.modules() if isinstance(m, nn.ConvTranspose2d)]
    assert [m.output_padding[0] for m in deconvs] == [1, 0, 1, 1, 1, 1, 1]  # 2 -> 4 -> 7 -> 14 ...
    assert isinstance(net.decoder[-1][-1], nn.ConvTranspose2d)  # no BN, no output activation
    assert deconvs[-1].out_channels == 3


def test_odd_pair_channels_are_refused(make_cfg, on_disk):
    from rotlearn.config import validate

    cfg = make_cfg(["experiment=kitti_autoencoder", "net.pair_channels=3"])
    with pytest.raises(ConfigError, match=r"net\.pair_channels: should be a multiple of 2, got 3"):
        validate(on_disk(cfg))


# -- the module ---------------------------------------------------------------------------------


def test_loss_and_score_use_only_the_first_image():
    torch.manual_seed(0)
    module = AutoEncoderModule(tiny_autoencoder(), torch.optim.Adam)
    pairs = torch.randn(5, 6, 16, 16)
    other = pairs.clone()
    other[:, 3:] = torch.randn(5, 3, 16, 16)
    batch, other_batch = {"input": pairs}, {"input": other}
    assert torch.equal(module.training_step(batch, 0), module.training_step(other_batch, 0))
    module.eval()
    scores = module.score(pairs)
    assert torch.equal(scores, module.score(other))
    assert scores.shape == (5,) and bool((scores >= 0).all())
    first = pairs[:1, :3]
    expected = (module(first) - first).abs().mean()
    torch.testing.assert_close(scores[0], expected.detach())
    torch.testing.assert_close(module.score(pairs[1:3]), scores[1:3])  # per sample
    changed = pairs.clone()
    changed[0, :3] += 1.0
    assert not torch.equal(module.score(changed)[0], scores[0])


def test_score_rejects_a_wrong_channel_count():
    module = AutoEncoderModule(tiny_autoencoder(pair_channels=2)).eval()
    with pytest.raises(ValueError, match=re.escape("(B, 2, S, S)")):
        module.score(torch.randn(2, 6, 16, 16))


# -- configs, training and loading ---------------------------------------------------------------


@pytest.mark.parametrize("experiment", ["kitti_autoencoder", "mav_autoencoder"])
def test_experiments_select_the_autoencoder(make_cfg, experiment):
    cfg = make_cfg([f"experiment={experiment}"])
    assert cfg.model._target_ == "rotlearn.lit.AutoEncoderModule"
    assert cfg.net._target_ == "rotlearn.nets.ConvAutoEncoder"
    assert cfg.net.pair_channels == cfg.data.pair_channels
    assert cfg.optim.lr == 5e-4 and cfg.data.batch_size == 32 and cfg.trainer.max_epochs == 20
    assert cfg.callbacks.checkpoint.monitor == "val/loss"


def test_build_refuses_a_model_with_a_mismatched_net(make_cfg, on_disk):
    with pytest.raises(ConfigError, match=r"config key .*net: model=autoencoder trains net=auto"):
        build(make_cfg(["model=autoencoder"]))
    with pytest.raises(
        ConfigError, match=r"config key .*net: the auto-encoder .* model=autoencoder"
    ):
        build(on_disk(make_cfg(["net=autoencoder", "data=kitti"])))


def csv_column(run: Path, key: str) -> list[float]:
    with (run / "csv" / "metrics.csv").open() as f:
        return [float(row[key]) for row in csv.DictReader(f) if row.get(key)]


def test_train_score_and_load(make_cfg, tmp_path):
    still = {seq: [np.eye(3)] * n for seq, n in {"00": 9, "01": 17}.items()}
    root = write_kitti(tmp_path / "kitti", still, smooth=True)
    cfg = make_cfg(
        [
            "experiment=kitti_autoencoder",
            f"data.root={root}",
            "data.train_sequences=[01]",
            "data.test_sequences=[00]",
            "data.num_workers=0",
            "data.batch_size=4",
            "data.val_fraction=0.2",
            *TINY_NET,
            "optim.lr=1e-2",
            "trainer=cpu",
            "trainer.max_epochs=3",
            "trainer.enable_progress_bar=false",
            "logger=csv",
        ]
    )
    metrics = train(cfg)
    run = Path(cfg.paths.output_dir)
    assert metrics["task"] == "autoencoder" and "rep" not in metrics
    assert metrics["test/recon_mean"] > 0 and "best/val_loss" in metrics
    losses = csv_column(run, "train/loss")
    assert len(losses) == 3 and losses[-1] < losses[0]
    assert len(csv_column(run, "val/loss")) == 3

    module = load_autoencoder(run / "checkpoints" / "last.ckpt")
    assert not module.training and module.task == "autoencoder"
    datamodule = instantiate(cfg.data)
    datamodule.setup()
    scores = torch.cat(
        [module.score(datamodule.finish_batch(b)["input"]) for b in datamodule.test_dataloader()]
    )
    assert scores.shape == (8,) and bool((scores >= 0).all())
    assert float(scores.mean()) == pytest.approx(metrics["test/recon_mean"], rel=1e-5)
    pairs = torch.randn(2, 6, 16, 16)
    torch.testing.assert_close(load_autoencoder(run).score(pairs), module.score(pairs))  # run dir
    with pytest.raises(ValueError, match="is an auto-encoder checkpoint, not a rotation model"):
        rotlearn.load(run)  # rotlearn-predict's loader
    # rotlearn-eval on it: refused, saying where an auto-encoder run goes
    wanted = rf"{re.escape(str(run))} is an auto-encoder, not .*ood.autoencoder_ckpt="
    with pytest.raises(ConfigError, match=wanted):
        evaluation_config(OmegaConf.create({"ckpt": str(run)}), load_run(run))


def test_a_rotation_checkpoint_is_refused(make_cfg):
    cfg = make_cfg(["data=tiny", "trainer=cpu", "trainer.max_epochs=1", "logger=none", *SMALL_NET])
    metrics = train(cfg)
    assert metrics["task"] == "rotation" and metrics["rep"] == "a"
    assert "best/val_err_mean" in metrics and "test/recon_mean" not in metrics
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    with pytest.raises(
        ValueError, match=rf"{re.escape(str(ckpt))} is not an auto-encoder.*'rotation'"
    ):
        load_autoencoder(ckpt)
