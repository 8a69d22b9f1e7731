"""Issue 13: every config value is checked before the Trainer is built (Hydra compose API)."""

from __future__ import annotations

import inspect
import re
import typing

import lightning.pytorch as pl
import pytest
import torch
from omegaconf import OmegaConf

from rotlearn.cli.schemas import SCHEMAS, ConfigError, validate
from rotlearn.cli.signatures import accepts, describe, targets
from rotlearn.cli.train import build, train
from tests.conftest import CONFIG_DIR, config_options

GROUPS = sorted(p.name for p in CONFIG_DIR.iterdir() if p.is_dir() and p.name != "hydra")

BAD = [
    ("optim.lr=fast", r"optim\.lr: must be a positive number, got 'fast'"),
    ("optim.lr=-1", r"optim\.lr: must be a positive number, got -1"),
    ("optim.lr=0", r"optim\.lr: must be a positive number, got 0"),
    ("optim.weight_decay=-0.1", r"optim\.weight_decay: must be a number >= 0, got -0\.1"),
    ("+optim.betaz=1", r"optim\.betaz: unknown \(did you mean optim\.betas\?\); allowed: lr, "),
    ("+optim.betas=[0.9,1.5]", r"optim\.betas: must be a list of numbers in \[0, 1\)"),
    ("+optim.amsgrad=maybe", r"optim\.amsgrad: expected bool, got 'maybe'"),
    ("trainer.max_epochs=two", r"trainer\.max_epochs: must be a positive integer, got 'two'"),
    ("trainer.max_epochs=-1", r"trainer\.max_epochs: must be a positive integer \(.*forever"),
    ("trainer.max_epochs=0", r"trainer\.max_epochs: must be a positive integer \(.*, got 0"),
    ("trainer.max_epochs=2.5", r"trainer\.max_epochs: must be a positive integer, got 2\.5"),
    ("trainer.max_epochs=null", r"trainer\.max_epochs: must be a positive integer, got None"),
    ("trainer.precision=17", r"trainer\.precision: expected one of 64, 32, 16, .*'32-true'.*17"),
    ("trainer.precision=bf17-mixed", r"trainer\.precision: expected one of .*'bf16-mixed'"),
    ("+trainer.bogus=1", r"trainer\.bogus: unknown; allowed: accelerator, strategy, devices, "),
    ("+trainer.max_epoch=3", r"trainer\.max_epoch: unknown \(did you mean trainer\.max_epochs\?"),
    ("trainer.devices=0", r"trainer\.devices: must be a positive integer, -1 \(every device\)"),
    ("trainer.devices=[]", r"trainer\.devices: must be a positive integer"),
    ("trainer.accelerator=gpus", r"trainer\.accelerator: must be a accelerator Lightning knows: "),
    ("+trainer.strategy=dddp", r"trainer\.strategy: must be a strategy Lightning knows: .*ddp"),
    ("trainer.enable_progress_bar=maybe", r"trainer\.enable_progress_bar: expected bool or None"),
    ("trainer.log_every_n_steps=0", r"trainer\.log_every_n_steps: must be a positive integer or"),
    ("trainer.fast_dev_run=-2", r"trainer\.fast_dev_run: must be true, false or a number"),
    ("trainer.num_sanity_val_steps=-2", r"trainer\.num_sanity_val_steps: must be an integer >= -1"),
    ("+trainer.logger=false", r"trainer\.logger: unknown"),  # rotlearn passes the loggers
    ("float32_matmul_precision=bogus", r"float32_matmul_precision: must be 'highest', 'high' or"),
    ("seed=abc", r"config key seed: expected int, got 'abc'"),
    ("seed=-1", r"config key seed: must lie in \[0, 4294967295\], got -1"),
    ("+bogus_top=1", r"config key bogus_top: unknown; allowed: calibrate, callbacks, ckpt_path, "),
    ("+sed=1", r"config key sed: unknown \(did you mean seed\?\)"),
    ("test_ckpt=worst", r"config key test_ckpt: must be 'last' or 'best', got 'worst'"),
    ("+task=rotation", r"config key task: unknown"),  # model=regressor|autoencoder instead
    ("ckpt_path=5", r"config key ckpt_path: expected str or None, got 5"),
    ("+paths.log_dir=x", r"config key paths\.log_dir: unknown; allowed: output_dir"),
    (
        "+logger.tensorboard.save_dirr=x",
        r"logger\.tensorboard\.save_dirr: unknown \(did you mean logger\.tensorboard\.save_dir\?",
    ),
    ("+logger.tensorboard.flush_secs=fast", r"logger\.tensorboard\.flush_secs"),  # SummaryWriter's
    ("logger.tensorboard.default_hp_metric=2", r"logger\.tensorboard\.default_hp_metric: expected"),
    ("+callbacks.checkpoint.mode=maximum", r"callbacks\.checkpoint\.mode: must be one of min, max"),
    ("+callbacks.checkpoint.save_top_k=-2", r"callbacks\.checkpoint\.save_top_k: must be an integ"),
    ("+callbacks.checkpoint.monitr=x", r"callbacks\.checkpoint\.monitr: unknown \(did you mean "),
    ("callbacks.checkpoint=null", r"callbacks\.checkpoint: must be a mapping .*~callbacks\.check"),
    ("+callbacks.epoch_timer.every=2", r"callbacks\.epoch_timer\.every: unknown; allowed: $"),
    ("net.head_channels=[]", r"net\.head_channels: must be a non-empty list of positive integ"),
    ("net.center_init=1", r"net\.center_init: expected bool, got 1"),
    ("+net.dropout=0.1", r"net\.dropout: unknown; allowed: out_dim, in_channels, point_channels"),
    ("optim.lr=${nope}", r"config key optim\.lr: cannot be resolved"),
]


@pytest.mark.parametrize(("override", "message"), BAD, ids=[o for o, _ in BAD])
def test_a_bad_value_is_refused_naming_its_key(make_cfg, override, message):
    key = re.split(r"[=+]", override.lstrip("+"))[0]
    with pytest.raises(ConfigError, match=message) as err:
        validate(make_cfg([override]))
    assert str(err.value).startswith(f"config key {key}")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["callbacks=ood", "callbacks.ood.corrupt_fraction=half"], r"callbacks\.ood\.corrupt_f"),
        (["callbacks=ood", "+callbacks.ood.quantile=[1]"], r"did you mean callbacks\.ood\.quant"),
        (["data=kitti", "net.hidden=0"], r"net\.hidden: must be a positive integer, got 0"),
        (["experiment=kitti_autoencoder", "net.latent=-3"], r"net\.latent: must be a positive"),
        (["sweep=lr", "trials=0"], r"config key trials: must lie in \[1, "),
        (["sweep=lr", "lr_range=[1e-4]"], r"config key lr_range: expected a list of float"),
        (["logger=csv", "+logger.csv.flush_logs_every_n_steps=x"], r"logger\.csv\.flush_logs_e"),
    ],
)
def test_bad_values_of_other_options_are_refused(make_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate(make_cfg(overrides))


SCHEDULER = "+scheduler={_target_: torch.optim.lr_scheduler.StepLR, _partial_: true, step_size: %s}"


def test_an_optional_scheduler_is_checked_when_present(make_cfg):
    validate(make_cfg([SCHEDULER % 10]))
    with pytest.raises(ConfigError, match=r"scheduler\.step_size: must be a positive integer"):
        validate(make_cfg([SCHEDULER % 0]))
    with pytest.raises(ConfigError, match=r"scheduler\.optimizer: unknown"):  # passed by the model
        validate(make_cfg([SCHEDULER % 10, "+scheduler.optimizer=x"]))


def test_another_torch_optimizer_is_checked_by_its_own_signature(make_cfg):
    sgd = ["optim._target_=torch.optim.SGD", "~optim.weight_decay", "+optim.momentum=0.9"]
    validate(make_cfg(sgd))
    with pytest.raises(ConfigError, match=r"optim\.momentum: must be a number >= 0"):
        validate(make_cfg([*sgd[:2], "+optim.momentum=-0.9"]))
    with pytest.raises(ConfigError, match=r"optim\.betas: unknown; allowed: lr, momentum, "):
        validate(make_cfg([*sgd[:2], "+optim.betas=[0.9,0.99]"]))


def test_a_users_own_target_is_left_to_its_constructor(make_cfg):
    validate(make_cfg(["+callbacks.mine={_target_: my.package.Callback, anything: 1}"]))


@pytest.mark.parametrize("group", GROUPS)
def test_every_option_of_every_group_validates(make_cfg, group):
    assert config_options(group)
    # a group that conf/train.yaml's defaults do not name (variant: experiment=beliefs's) is added
    defaults = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "train.yaml").defaults)
    named = {next(iter(d)) for d in defaults if isinstance(d, dict)}
    add = "" if group in named else "+"
    for option in config_options(group):
        images = group == "net" and option != "pointnet"  # their sizes come from an image dataset
        validate(make_cfg([f"{add}{group}={option}", *(["data=kitti"] if images else [])]))


def test_the_trainers_allowed_keys_are_its_signatures():
    spec = targets()["trainer"]["lightning.pytorch.Trainer"]
    expected = set(inspect.signature(pl.Trainer.__init__).parameters) - {"self"}
    assert set(spec.allowed) == expected - {"callbacks", "logger"}
    optimizers = targets()["optim"]
    assert {"torch.optim.Adam", "torch.optim.AdamW", "torch.optim.SGD"} <= set(optimizers)
    assert "params" not in optimizers["torch.optim.Adam"].allowed


def test_precision_values_come_from_lightnings_annotation():
    annotation = typing.get_type_hints(pl.Trainer.__init__)["precision"]
    for value in ("32-true", "bf16-mixed", "16-mixed", 32, "64", None):
        assert accepts(value, annotation), value
    for value in (17, "32-True", 32.0, True):
        assert not accepts(value, annotation), value
    assert "'bf16-mixed'" in describe(annotation) and describe(annotation).endswith("or None")


def test_each_dataclass_target_is_not_also_read_from_a_signature():
    for group, schemas in SCHEMAS.items():
        assert not set(schemas) & set(targets().get(group, {})), group


def test_build_validates_before_anything_is_built(make_cfg, monkeypatch):
    def no_trainer(*args, **kwargs):
        raise AssertionError("the Trainer was built")

    monkeypatch.setattr(pl, "Trainer", no_trainer)
    with pytest.raises(ConfigError, match=r"trainer\.max_epochs"):
        build(make_cfg(["trainer.max_epochs=-1"]))


def test_a_resumed_run_is_validated_before_it_trains(make_cfg, tmp_path, monkeypatch):
    ckpt = tmp_path / "old" / "last.ckpt"
    ckpt.parent.mkdir()
    torch.save({}, ckpt)
    monkeypatch.setattr(pl.Trainer, "fit", lambda *a, **k: pytest.fail("trained"))
    with pytest.raises(ConfigError, match=r"config key optim\.lr: must be a positive number"):
        train(make_cfg([f"ckpt_path={ckpt}", "data=tiny", "optim.lr=fast"]))


def test_the_ood_callback_is_checked_under_any_name(make_cfg):
    ood = "+callbacks.mine={_target_: rotlearn.ood.OODEvaluation, noise_pairs: many}"
    with pytest.raises(ConfigError, match=r"callbacks\.mine\.noise_pairs: expected int"):
        validate(make_cfg(["data=kitti", ood]))
