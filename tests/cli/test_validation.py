"""Issues 13 and 23: every config value is checked before the Trainer is built (compose API)."""

from __future__ import annotations

import inspect
import re
from typing import Any

import lightning.pytorch as pl
import pytest
import torch
from omegaconf import OmegaConf

from rotlearn.cli.train import build, train
from rotlearn.config import ConfigError, validate
from rotlearn.config.checks import arguments
from tests.conftest import CONFIG_DIR, config_options

GROUPS = sorted(p.name for p in CONFIG_DIR.iterdir() if p.is_dir() and p.name != "hydra")

BAD = [
    ("optim.lr=fast", r"optim\.lr: should be a valid number, got 'fast'"),
    ("optim.lr=-1", r"optim\.lr: should be greater than 0, got -1"),
    ("optim.lr=0", r"optim\.lr: should be greater than 0, got 0"),
    ("optim.weight_decay=-0.1", r"optim\.weight_decay: should be greater than or equal to 0, got"),
    ("+optim.betaz=1", r"optim\.betaz: unknown key; did you mean optim\.betas\?; allowed: lr, "),
    ("+optim.betas=[0.9,1.5]", r"optim\.betas: should be less than 1 \(at \[1\]\), got \[0\.9"),
    ("+optim.amsgrad=maybe", r"optim\.amsgrad: should be a valid boolean, got 'maybe'"),
    ("trainer.max_epochs=two", r"trainer\.max_epochs: must be a positive integer .*, got 'two'"),
    ("trainer.max_epochs=-1", r"trainer\.max_epochs: must be a positive integer \(.*forever"),
    ("trainer.max_epochs=0", r"trainer\.max_epochs: must be a positive integer \(.*, got 0"),
    ("trainer.max_epochs=2.5", r"trainer\.max_epochs: must be a positive integer .*, got 2\.5"),
    ("trainer.max_epochs=null", r"trainer\.max_epochs: must be a positive integer .*, got None"),
    ("trainer.precision=17", r"trainer\.precision: should be 64, 32 or 16 or .*'32-true'.*17"),
    ("trainer.precision=bf17-mixed", r"trainer\.precision: should be .*'bf16-mixed'"),
    ("+trainer.bogus=1", r"trainer\.bogus: unknown key; allowed: accelerator, strategy, devices, "),
    ("+trainer.max_epoch=3", r"trainer\.max_epoch: unknown key; did you mean trainer\.max_epoch"),
    ("trainer.devices=0", r"trainer\.devices: must be a positive integer, -1 \(every device\)"),
    ("trainer.devices=[]", r"trainer\.devices: must be a positive integer"),
    ("trainer.accelerator=gpus", r"trainer\.accelerator: should be the name of an accelerator Li"),
    ("+trainer.strategy=dddp", r"trainer\.strategy: should be the name of a strategy .*ddp"),
    ("trainer.enable_progress_bar=maybe", r"trainer\.enable_progress_bar: should be a valid bool"),
    ("trainer.log_every_n_steps=0", r"trainer\.log_every_n_steps: should be greater than 0"),
    ("trainer.fast_dev_run=-2", r"trainer\.fast_dev_run: must be true, false or a number"),
    ("trainer.num_sanity_val_steps=-2", r"trainer\.num_sanity_val_steps: must be an integer >= -1"),
    ("+trainer.logger=false", r"trainer\.logger: unknown key"),  # rotlearn passes the loggers
    ("float32_matmul_precision=bogus", r"float32_matmul_precision: should be 'highest', 'high' or"),
    ("seed=abc", r"config key seed: should be a valid integer, got 'abc'"),
    ("seed=-1", r"config key seed: should be greater than or equal to 0, got -1"),
    ("+bogus_top=1", r"config key bogus_top: unknown key; allowed: calibrate, callbacks, ckpt_pa"),
    ("+sed=1", r"config key sed: unknown key; did you mean seed\?"),
    ("test_ckpt=worst", r"config key test_ckpt: should be 'last' or 'best', got 'worst'"),
    ("+task=rotation", r"config key task: unknown key"),  # model=regressor|autoencoder instead
    ("ckpt_path=5", r"config key ckpt_path: should be a valid string, got 5"),
    ("+paths.log_dir=x", r"config key paths\.log_dir: unknown key; allowed: output_dir"),
    (
        "+logger.tensorboard.save_dirr=x",
        r"logger\.tensorboard\.save_dirr: unknown key; did you mean logger\.tensorboard\.save_di",
    ),
    ("+logger.tensorboard.flush_secs=fast", r"logger\.tensorboard\.flush_secs"),  # SummaryWriter's
    ("logger.tensorboard.default_hp_metric=2", r"logger\.tensorboard\.default_hp_metric: should"),
    ("+callbacks.checkpoint.mode=maximum", r"callbacks\.checkpoint\.mode: should be 'min' or 'ma"),
    ("+callbacks.checkpoint.save_top_k=-2", r"callbacks\.checkpoint\.save_top_k: should be great"),
    ("+callbacks.checkpoint.monitr=x", r"callbacks\.checkpoint\.monitr: unknown key; did you mea"),
    ("callbacks.checkpoint=null", r"callbacks\.checkpoint: must be a mapping .*~callbacks\.check"),
    ("+callbacks.epoch_timer.every=2", r"callbacks\.epoch_timer\.every: unknown key; allowed: no"),
    ("net.head_channels=[]", r"net\.head_channels: should have at least 1 item, not 0, got \[\]"),
    ("net.center_init=1", r"net\.center_init: should be a valid boolean, got 1"),
    ("+net.dropout=0.1", r"net\.dropout: unknown key; allowed: out_dim, in_channels, point_chann"),
    ("optim.lr=${nope}", r"config key optim\.lr: cannot be resolved"),
    ("report={trial_keys: 5}", r"config key report\.trial_keys: should be a valid list, got 5"),
    (  # the report a sweep writes when it ends: refused before it starts, not after
        "report={plots: [{kind: curves, file: ../curves.png}]}",
        r"report\.plots\[0\]\.file: should be a plain file name ending in \.png .*'\.\./curv",
    ),
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
        (
            ["data=kitti", "callbacks=ood", "callbacks.ood.corrupt_fraction=half"],
            r"callbacks\.ood\.corrupt_f",
        ),
        (["callbacks=ood", "+callbacks.ood.quantile=[1]"], r"did you mean callbacks\.ood\.quant"),
        (["data=kitti", "net.hidden=0"], r"net\.hidden: should be greater than 0, got 0"),
        (["experiment=kitti_autoencoder", "net.latent=-3"], r"net\.latent: should be greater th"),
        (["sweep=lr", "trials=0"], r"config key trials: should be greater than or equal to 1"),
        (["sweep=lr", "lr_range=[1e-4]"], r"config key lr_range: should have at least 2 items"),
        (["logger=csv", "+logger.csv.flush_logs_every_n_steps=x"], r"logger\.csv\.flush_logs_e"),
    ],
)
def test_bad_values_of_other_options_are_refused(make_cfg, on_disk, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate(on_disk(make_cfg(overrides)))


SCHEDULER = "+scheduler={_target_: torch.optim.lr_scheduler.StepLR, _partial_: true, step_size: %s}"


def test_an_optional_scheduler_is_checked_when_present(make_cfg):
    validate(make_cfg([SCHEDULER % 10]))
    with pytest.raises(ConfigError, match=r"scheduler\.step_size: should be greater than 0"):
        validate(make_cfg([SCHEDULER % 0]))
    with pytest.raises(ConfigError, match=r"scheduler\.optimizer: unknown"):  # passed by the model
        validate(make_cfg([SCHEDULER % 10, "+scheduler.optimizer=x"]))


def test_another_torch_optimizer_is_checked_by_its_own_signature(make_cfg):
    sgd = ["optim._target_=torch.optim.SGD", "~optim.weight_decay", "+optim.momentum=0.9"]
    validate(make_cfg(sgd))
    with pytest.raises(ConfigError, match=r"optim\.momentum: should be greater than or equal to 0"):
        validate(make_cfg([*sgd[:2], "+optim.momentum=-0.9"]))
    with pytest.raises(ConfigError, match=r"optim\.betas: unknown key; allowed: lr, momentum, "):
        validate(make_cfg([*sgd[:2], "+optim.betas=[0.9,0.99]"]))


LIBRARY_MODULES = [
    ("lightning.pytorch.callbacks", "callbacks"),
    ("lightning.pytorch.loggers", "logger"),
    ("torch.optim", "optim"),
    ("torch.optim.lr_scheduler", "scheduler"),
]


def _library_classes(module: str) -> list[str]:
    """The dotted names of the classes a user may name from `module`."""
    from hydra.utils import get_object

    found = get_object(module)
    return [f"{module}.{n}" for n, c in vars(found).items()
            if inspect.isclass(c) and c.__module__.startswith(module)]  # fmt: skip


@pytest.mark.parametrize(("module", "group"), LIBRARY_MODULES)
def test_every_library_class_accepts_its_own_defaults(module, group):
    """Every class a user may name from these modules is read (keys) and each literal default
    passes the check of its own annotation: a tuple default written as a YAML list, an object
    default (`NOT_LITERAL`) skipped. Both once failed (a crash, 9 refusals)."""
    from rotlearn.config.checks import _annotation, _check, _imported_annotation
    from rotlearn.config.source import MISSING, NOT_LITERAL

    classes = _library_classes(module)
    assert len(classes) >= 5
    for target in classes:
        for p in arguments(target, group) or ():
            if p.default is not NOT_LITERAL and p.default != MISSING:
                annotation = _annotation(p) or _imported_annotation(p.owner, p.name)
                _check(f"{group}.{p.name}", p.default, annotation)


def test_an_annotation_read_from_source_is_the_imported_one():
    """A value is first checked against the annotation its source text tells, nothing imported
    (a refusal in a second, not after Lightning loads). Where that text names only builtins,
    typing and annotated-types constructs, it is the annotation of the imported constructor:
    every rotlearn component's and library class's argument (where the import reads no more than
    any, for names its module imports for type checkers only, the source says more)."""
    from rotlearn.config.checks import _annotation, _imported_annotation
    from rotlearn.config.source import marked

    targets = [(t, "") for t in marked()]
    targets += [(t, group) for module, group in LIBRARY_MODULES for t in _library_classes(module)]
    read = []
    for target, group in targets:
        for p in arguments(target, group) or ():
            if p.annotation is not None and (annotation := _annotation(p)) is not None:
                imported = _imported_annotation(p.owner, p.name)  # Any: names it cannot see
                assert annotation == imported or imported is Any, (target, p.name)
                read.append(p.name)
    assert len(read) > 150 and {"batch_size", "phi_max_deg", "foreach", "monitor"} <= set(read)


def test_a_tuple_argument_takes_a_yaml_list(make_cfg):
    """Rprop's `etas: tuple[float, float]` is written as a list in YAML; it was refused as 'no
    valid tuple' whatever the value. Its elements and length are still checked."""
    rprop = ["optim._target_=torch.optim.Rprop", "~optim.weight_decay"]
    validate(make_cfg([*rprop, "+optim.etas=[0.4,1.3]", "+optim.step_sizes=[1e-6,10]"]))
    with pytest.raises(ConfigError, match=r"optim\.etas: .*got \['x', 1\.3\]"):
        validate(make_cfg([*rprop, "+optim.etas=[x,1.3]"]))
    with pytest.raises(ConfigError, match=r"optim\.etas: .*got \[0\.4, 1\.3, 2\.0\]"):
        validate(make_cfg([*rprop, "+optim.etas=[0.4,1.3,2.0]"]))
    with pytest.raises(ConfigError, match=r"lr_range: should be greater than 0 \(at \[0\]\)"):
        validate(make_cfg(["+lr_range=[-1.0,1.0]"]))  # a list argument keeps its own message


def test_a_library_callback_with_an_object_as_a_default_is_checked(make_cfg):
    """Lightning's SWA defaults `device` to `torch.device("cpu")`, no literal: its keys and
    values are still checked (the source reader crashed on it, a traceback before training)."""
    swa = ["+callbacks.swa._target_=lightning.pytorch.callbacks.StochasticWeightAveraging",
           "+callbacks.swa.swa_lrs=0.001"]  # fmt: skip
    validate(make_cfg(swa))
    with pytest.raises(ConfigError, match=r"callbacks\.swa\.swa_lr: unknown key; did you mean "
                                          r"callbacks\.swa\.swa_lrs\?"):  # fmt: skip
        validate(make_cfg([swa[0], "+callbacks.swa.swa_lr=0.001"]))
    with pytest.raises(ConfigError, match=r"callbacks\.swa\.swa_lrs: .*got 'fast'"):
        validate(make_cfg([swa[0], "+callbacks.swa.swa_lrs=fast"]))


def test_a_users_own_target_is_left_to_its_constructor(make_cfg):
    validate(make_cfg(["+callbacks.mine={_target_: my.package.Callback, anything: 1}"]))


@pytest.mark.parametrize("group", GROUPS)
def test_every_option_of_every_group_validates(make_cfg, on_disk, group):
    assert config_options(group)
    # a group that conf/train.yaml's defaults do not name (variant: experiment=beliefs's) is added
    defaults = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "train.yaml").defaults)
    named = {next(iter(d)) for d in defaults if isinstance(d, dict)}
    add = "" if group in named else "+"
    for option in config_options(group):
        images = group == "net" and option != "pointnet"  # their sizes come from an image dataset
        images |= group == "callbacks" and option == "ood"  # it scores image pairs
        needs = ["data=kitti"] if images else []
        needs += ["rep=fisher"] if option == "fisher_nll" else []
        validate(on_disk(make_cfg([f"{add}{group}={option}", *needs])))


def test_the_trainers_allowed_keys_are_its_signatures():
    allowed = {p.name for p in arguments("lightning.pytorch.Trainer", "trainer")}
    expected = set(inspect.signature(pl.Trainer.__init__).parameters) - {"self"}
    assert allowed == expected - {"callbacks", "logger"}
    for name in ("Adam", "AdamW", "SGD"):
        optimizer = getattr(torch.optim, name)
        expected = set(inspect.signature(optimizer.__init__).parameters) - {"self", "params"}
        assert {p.name for p in arguments(f"torch.optim.{name}", "optim")} == expected


@pytest.mark.parametrize("value", ["32-true", "bf16-mixed", "16-mixed", 32, "64", None])
def test_precision_values_come_from_lightnings_annotation(make_cfg, value):
    validate(make_cfg([f"trainer.precision={'null' if value is None else value}"]))


@pytest.mark.parametrize("value", [17, "32-True", 32.0, True])
def test_other_precision_values_are_refused(make_cfg, value):
    with pytest.raises(ConfigError, match=r"trainer\.precision: should be .*'bf16-mixed'|integer"):
        validate(make_cfg([f"trainer.precision={value}"]))


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
    with pytest.raises(ConfigError, match=r"config key optim\.lr: should be a valid number"):
        train(make_cfg([f"ckpt_path={ckpt}", "data=tiny", "optim.lr=fast"]))


def test_the_ood_callback_is_checked_under_any_name(make_cfg, on_disk):
    ood = "+callbacks.mine={_target_: rotlearn.ood.OODEvaluation, noise_pairs: many}"
    with pytest.raises(ConfigError, match=r"callbacks\.mine\.noise_pairs: should be a valid int"):
        validate(on_disk(make_cfg(["data=kitti", ood])))


def test_a_sweep_is_checked_job_by_job_or_value_by_value():
    """`rotlearn.config.sweep_values`: every job of a sweep of at most CHECKED_JOBS (a pair of
    values that do not go together is found), else each other value of each swept key with the
    others at their first (of a range: its last)."""
    from rotlearn.config import CHECKED_JOBS, sweep_values

    def jobs(args):
        return [(v["rep"]["name"], v["loss"]["_target_"].rsplit(".")[-1], v["seed"])
                for v in sweep_values(args)]  # fmt: skip

    assert jobs(["rep=a"]) == []  # no sweep: nothing more than the command line's own config
    product = [("a", "AngularLoss", 3), ("quat", "ChordalLoss", 3), ("quat", "AngularLoss", 3)]
    assert jobs(["-m", "rep=a,quat", "loss=chordal,angular", "seed=3"]) == product
    assert CHECKED_JOBS < 2 * 20
    assert jobs(["-m", "rep=a,quat", "seed=range(0,20)"]) == [
        ("quat", "ChordalLoss", 0), ("a", "ChordalLoss", 19)]  # fmt: skip


def test_a_data_roots_layout_is_listed_a_value_at_a_time_in_the_order_given():
    """The paths a root must hold, as a missing one is named: a sequence's frames then its
    poses, the sequences in the order the config lists them (they were sorted as text: 01, 10,
    02 for [2, 10, 1]), a value listed twice once."""
    from rotlearn.config.checks import data_paths

    node = {"_target_": "rotlearn.data.kitti.KittiOdometryDataModule", "root": "/r",
            "train_sequences": [2, 10, 1], "test_sequences": [9, 10], "val_sequences": ["03"],
            "camera": "image_2"}  # fmt: skip
    found = [(key, str(path)) for key, path in data_paths(node)]
    assert found[0] == ("data.root", "/r")
    names = list(dict.fromkeys(path.removeprefix("/r/") for _, path in found[1:]))
    assert names == [kind for seq in ("02", "10", "01", "09", "03")
                     for kind in (f"sequences/{seq}/image_2", f"poses/{seq}.txt")]  # fmt: skip
    assert found[1][0] == "data.train_sequences" and found[-1][0] == "data.val_sequences"
