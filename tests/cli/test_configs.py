"""Every option of every config group composes and instantiates (Hydra compose API)."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest
import torch
from hydra.utils import get_object, instantiate
from lightning.pytorch import Callback, LightningDataModule, Trainer
from lightning.pytorch.loggers import Logger
from omegaconf import OmegaConf

from rotlearn.cli.train import build
from rotlearn.config import ConfigError, compose, register_schemas, schema, validate
from rotlearn.config.source import marked
from rotlearn.heads import HEADS, RotationHead
from tests.conftest import CONFIG_DIR, config_options, demo_overrides


def test_groups_have_the_documented_options():
    assert set(config_options("rep")) >= {"quat", "sixd", "a", "svd9d"}
    assert set(config_options("rep")) == set(HEADS)
    assert set(config_options("trainer")) >= {"default", "cpu", "gpu", "ddp", "ddp_cpu"}
    assert set(config_options("logger")) >= {"tensorboard", "csv", "none"}
    assert set(config_options("loss")) >= {"chordal", "angular"}


@pytest.mark.parametrize("rep", config_options("rep"))
def test_rep_builds_its_head_and_sizes_the_net(make_cfg, rep):
    cfg = make_cfg([f"rep={rep}"])
    head = instantiate(cfg.rep)
    assert isinstance(head, RotationHead) and head.name == rep
    assert head.out_dim == cfg.rep.out_dim == cfg.net.out_dim
    net = instantiate(cfg.net)
    assert net(torch.randn(3, 20, 6)).shape == (3, head.out_dim)


@pytest.mark.parametrize("data", config_options("data"))
def test_data_option_instantiates(make_cfg, demo_data, data):
    dm = instantiate(make_cfg([f"data={data}", *demo_overrides(demo_data, data)]).data)
    assert isinstance(dm, LightningDataModule)
    dm.setup("fit")
    if hasattr(dm, "draw"):  # drawn on the device
        batch = dm.draw(0, 0, 4)
    else:  # image pairs read from disk
        batch = dm.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
        batch = {k: v[:4] for k, v in batch.items()}
    assert batch["input"].shape[0] == 4 and batch["R"].shape == (4, 3, 3)
    assert batch["input"].is_floating_point()


@pytest.mark.parametrize("loss", config_options("loss"))
def test_loss_option_gives_a_scalar(make_cfg, loss):
    rep = {"fisher_nll": "fisher"}.get(loss, "a")  # a head the loss accepts
    cfg = make_cfg([f"rep={rep}", f"loss={loss}"])
    head, loss_fn = instantiate(cfg.rep), instantiate(cfg.loss)
    raw = torch.randn(5, head.out_dim, requires_grad=True)
    value = loss_fn(head(raw), {"R": head(torch.randn(5, head.out_dim)).R})
    assert value.ndim == 0 and torch.isfinite(value)
    value.backward()
    assert torch.isfinite(raw.grad).all()


@pytest.mark.parametrize("optim", config_options("optim"))
def test_optim_option_is_a_partial_optimizer(make_cfg, optim):
    cfg = make_cfg([f"optim={optim}", "optim.lr=0.123"])
    optimizer = instantiate(cfg.optim)([torch.nn.Parameter(torch.zeros(2))])
    assert isinstance(optimizer, torch.optim.Optimizer)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(0.123)


@pytest.mark.parametrize("trainer", config_options("trainer"))
def test_trainer_option(make_cfg, trainer):
    cfg = make_cfg([f"trainer={trainer}"])
    if cfg.trainer.accelerator == "gpu" and not torch.cuda.is_available():
        assert cfg.trainer.devices in (1, -1)  # composes; instantiating needs a GPU
        return
    assert isinstance(instantiate(cfg.trainer, logger=False, enable_checkpointing=False), Trainer)


@pytest.mark.parametrize("logger", config_options("logger"))
def test_logger_option(make_cfg, logger):
    loggers = [instantiate(node) for node in make_cfg([f"logger={logger}"]).logger.values()]
    assert all(isinstance(lg, Logger) for lg in loggers)
    assert (logger == "none") == (not loggers)


@pytest.mark.parametrize("callbacks", config_options("callbacks"))
def test_callbacks_option(make_cfg, callbacks):
    built = [instantiate(node) for node in make_cfg([f"callbacks={callbacks}"]).callbacks.values()]
    assert all(isinstance(cb, Callback) for cb in built)


def test_whole_config_builds_model_data_and_trainer(make_cfg):
    model, datamodule, trainer = build(make_cfg(["trainer=cpu"]))
    assert model.head.name == "a" and trainer.max_epochs == 50
    assert isinstance(datamodule, LightningDataModule)
    assert OmegaConf.select(OmegaConf.create(model.run_config), "rep.name") == "a"


COMPONENT_GROUPS = ("model", "rep", "net", "data", "loss")


@pytest.mark.parametrize("group", COMPONENT_GROUPS)
def test_every_option_of_a_component_group_validates(make_cfg, on_disk, group):
    for option in config_options(group):
        needs = {"fisher_nll": ["rep=fisher"], "autoencoder": ["experiment=kitti_autoencoder"]}
        images = ["data=kitti"] if group == "net" and option != "pointnet" else []
        validate(on_disk(make_cfg([f"{group}={option}", *needs.get(option, images)])))


@pytest.mark.parametrize("target", marked())
def test_schemas_match_their_targets_signatures(target):
    """Every constructor argument (those a subclass passes on with **kwargs included) is a key of
    the schema read from the source, with the same default; a list default equals the
    argument's tuple; a required argument is `???`."""
    obj = get_object(target)
    classes = [c for c in obj.__mro__ if "__init__" in vars(c)] if inspect.isclass(obj) else []
    functions = [c.__init__ for c in classes] or [obj]
    params: dict = {}
    for function in functions:
        signature = inspect.signature(function).parameters
        for name, p in signature.items():
            if name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
                params.setdefault(name, p.default)
        if not any(p.kind is p.VAR_KEYWORD for p in signature.values()):
            break
    node = schema(target)
    assert node.pop("_target_") == target
    assert list(node) == list(params)
    for name, default in params.items():
        expected = "???" if default is inspect.Parameter.empty else default
        assert node[name] == (list(expected) if isinstance(expected, tuple) else expected), name


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "+data.phi_maxdeg=3",
            r"data\.phi_maxdeg: unknown key; did you mean data\.phi_max_deg\?; allowed: ",
        ),
        ("data.phi_maxdeg=3", r"data\.phi_maxdeg: unknown key; did you mean data\.phi_max_deg"),
        ("data.phi_max_deg=abc", r"data\.phi_max_deg: should be a valid number, got 'abc'"),
        ("data.num_matches=2.5", r"data\.num_matches: should be a valid integer, got 2\.5"),
        ("data.redraw_test=maybe", r"data\.redraw_test: should be a valid boolean"),
        ("rep.out_dim=7", r"rep\.out_dim: is 7 but the 'a' head outputs 10"),
        ("+loss.weight=2", r"loss\.weight: unknown key; allowed: none"),
        (  # an element of a list the YAML does not list: Hydra makes {'0': 0.5} of it
            "optim.betas.0=0.5",
            r"optim\.betas: should be a valid list, got \{'0': 0\.5\}; a list the config does "
            r"not hold yet is set whole: optim\.betas=\[\.\.\.\]$",
        ),
    ],
)
def test_misspelt_keys_and_wrong_types_fail_before_training(make_cfg, override, message):
    with pytest.raises(ConfigError, match=message):
        build(make_cfg([override]))


def test_unknown_rep_lists_the_allowed_options(make_cfg):
    with pytest.raises(ConfigError, match=r"config key rep: no option 'quaternion'; did you mean "
                       r"rep=quat\?; options: a, fisher, quat, sixd, svd9d$"):  # fmt: skip
        make_cfg(["rep=quaternion"])
    with pytest.raises(ConfigError, match=r"no option 'head_schema'; options: a, fisher, quat, "):
        make_cfg(["rep=head_schema"])  # schemas are no options


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("optim.lr=[1", r"config key optim\.lr: cannot read 'optim\.lr=\[1' \(no viable "),
        ("data.root=a,b]", r"config key data\.root: cannot read 'data\.root=a,b\]' \("),
        ("lr", r"config key lr: 'lr' is no key=value; a value with brackets"),
    ],
)
def test_an_override_the_grammar_cannot_read_is_named(make_cfg, override, message):
    with pytest.raises(ConfigError, match=message):
        make_cfg([override])


def test_a_misspelt_key_of_hydras_gets_the_nearest_not_hydras_advice_to_append_it(make_cfg):
    """Hydra answered `hydra.run.dirr=x` with "To append to your config use +hydra.run.dirr=x"."""
    with pytest.raises(ConfigError, match=r"^config key hydra\.sweeper\.paramz: unknown key; did "
                       r"you mean hydra\.sweeper\.params\?; allowed: _target_, max_batch_size, "
                       r"params$"):  # fmt: skip
        make_cfg(["hydra.sweeper.paramz.rep=a"])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("~optim.lrr", r"^config key optim\.lrr: unknown key; did you mean optim\.lr\?; allowed: "
                       r"_partial_, _target_, lr, weight_decay; ~ deletes a key it has$"),
        ("~optimm", r"^config key optimm: unknown key; did you mean optim\?; allowed: calibrate, "),
        ("~optim.lr=1e-3", r"^config key optim\.lr: is 0\.0005, not 0\.001: ~optim\.lr=0\.001 "
                           r"deletes it only at that value; ~optim\.lr deletes it whatever it is$"),
    ],
)  # fmt: skip
def test_a_deletion_hydra_cannot_make_is_named_with_the_nearest_key(make_cfg, override, message):
    """Hydra answered `~optim.lrr` with "Could not delete from config. 'optim.lrr' does not
    exist." (no suggestion); a deletion that works still does."""
    with pytest.raises(ConfigError, match=message):
        make_cfg([override])
    assert "lr" not in make_cfg(["~optim.lr=0.0005"]).optim


def test_an_unknown_option_of_hydras_groups_lists_its_plugins_options(make_cfg):
    """`hydra/launcher=jobli` listed only conf/'s slurm.yaml (and `hydra/sweeper=optuan` nothing):
    the launchers and sweepers of Hydra and its plugins live in its ConfigStore."""
    with pytest.raises(ConfigError, match=r"^config key hydra/launcher: no option 'jobli'; did you "
                       r"mean hydra/launcher=joblib\?; options: basic, joblib, slurm, "
                       r"submitit_local, submitit_slurm$"):  # fmt: skip
        make_cfg(["hydra/launcher=jobli"])
    with pytest.raises(ConfigError, match=r"no option 'optuan'; did you mean "
                       r"hydra/sweeper=optuna\?; options: basic, optuna$"):  # fmt: skip
        make_cfg(["hydra/sweeper=optuan"])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("logger=null", r"^config key logger: takes one of its options \(csv, none, tensorboard\), "
                        r"not null; leave logger= out for the config's own choice$"),
        ("scheduler=null", r"^config key scheduler: takes one of its options \(cosine, step\), "),
        ("data=[kitti,mav]", r"^config key data: takes one of its options \(kitti, .*\), not a "
                             r"list; one run each: -m data=kitti,mav$"),
        ("variant=a_bingham", r"^config key variant: conf/train\.yaml chooses no variant; "
                              r"experiment=beliefs chooses one \(e\.g\. experiment=beliefs "
                              r"variant=a_bingham\)$"),
        ("paths=3", r"^config key paths: holds keys to set one by one, paths\.<key>=value "
                    r"\(output_dir\), not paths=3$"),
    ],
)  # fmt: skip
def test_a_config_group_or_node_hydra_would_misread_is_named(make_cfg, override, message):
    """Hydra answered `logger=null` with a ValueError traceback ("Config group override must be
    a string or a list"), `variant=a_bingham` with its advice to append it, `data=[kitti,mav]`
    by merging both options, and `paths=3` ended in an AttributeError; `experiment=beliefs
    variant=fisher_nll`, the way a variant is chosen, still composes."""
    with pytest.raises(ConfigError, match=message):
        make_cfg([override])
    assert make_cfg(["experiment=beliefs", "variant=fisher_nll"]).loss.rep == "fisher"
    assert set(make_cfg(["logger=[tensorboard,csv]"]).logger) == {"tensorboard", "csv"}


def test_rotlearn_evals_nodes_of_keys_take_no_option(make_cfg):
    """conf/eval.yaml's `data`, `trainer` and `ood` hold keys for the run's saved config:
    `data=kitti` got Hydra's advice to append it, `ood=kitti` and `ood=null` a ValueError."""
    for override, keys in [("data=kitti", "root, num_workers, eval_batch_size, corrupt_fraction"),
                           ("ood=null", "quantiles, thresholds_from, "),
                           ("trainer=gpu", "accelerator, devices")]:  # fmt: skip
        with pytest.raises(ConfigError, match=rf"^config key {override.split('=')[0]}: holds keys "
                           rf"to set one by one, \w+\.<key>=value \({keys}"):  # fmt: skip
            compose(["ckpt=run", override], config_name="eval", check=False)
    assert compose(["ckpt=run", "data.root=here"], config_name="eval", check=False).data.root


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("hydra.launcher.n_jobs=2", r"hydra\.launcher\.n_jobs: unknown key; allowed: _target_; "
         r"n_jobs is a setting of hydra/launcher=joblib$"),
        ("hydra.launcher.partition=gpu", r"hydra\.launcher\.partition: unknown key; allowed: "
         r"_target_; partition is a setting of hydra/launcher=slurm, submitit_slurm$"),
        ("hydra.launcher.n_jobz=2", r"hydra\.launcher\.n_jobz: unknown key; allowed: _target_$"),
    ],
)  # fmt: skip
def test_a_setting_of_another_launcher_names_the_launcher_that_has_it(make_cfg, override, message):
    """`hydra.launcher.n_jobs=2` under the basic launcher said only "allowed: _target_"."""
    with pytest.raises(ConfigError, match=message):
        make_cfg([override])


def test_plain_hydra_compose_needs_no_rotlearn_import_first(tmp_path):
    """conf/ composes with Hydra alone (the schemas and the configs' `${rl.*:}` resolvers
    register through rotlearn's Hydra plugin), in a fresh interpreter that imports nothing of
    rotlearn's."""
    code = (
        "from hydra import compose, initialize_config_dir\n"
        f"with initialize_config_dir(config_dir={str(CONFIG_DIR)!r}, version_base='1.3'):\n"
        "    cfg = compose('train', ['rep=a', 'loss=bingham', 'sweep=lr', 'trainer=gpu'])\n"
        "import sys\n"
        "print(cfg.loss._target_, cfg.data.phi_max_deg, 'torch' in sys.modules)\n"
        "print(cfg.optim.lr > 0, cfg.trainer.precision)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[:3] == ["rotlearn.losses.BinghamNLLLoss", "180.0", "False"]
    assert out.stdout.split()[3] == "True" and out.stdout.split()[4].endswith(("-true", "-mixed"))


def test_compose_from_python_resolves_the_configs_own_resolvers():
    """`rotlearn.config.compose` in a fresh interpreter, as a notebook calls it: sweep=lr's
    log-uniform lr and trainer=gpu's precision resolve (they did only after a CLI import)."""
    code = (
        "from rotlearn.config import compose\n"
        "cfg = compose(['sweep=lr', 'trial=3', 'trials=10', 'trainer=gpu'])\n"
        "from rotlearn.config.resolvers import loguniform_trial\n"
        "print(cfg.optim.lr == loguniform_trial(3, 10, cfg.sweep_seed, *cfg.lr_range))\n"
        "print(cfg.trainer.precision)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[0] == "True" and out.stdout.split()[1].endswith(("-true", "-mixed"))


def test_rep_name_typo_inside_a_config_names_the_key(make_cfg):
    with pytest.raises(ConfigError, match=r"rep\.name: unknown rep 'quaternion'; allowed: a, "):
        build(make_cfg(["rep.name=quaternion"]))


@pytest.mark.parametrize("bad", [0, -10, 180.5, 360])
def test_phi_max_outside_range_is_refused_naming_the_key(make_cfg, bad):
    should = r"should be (greater than 0|less than or equal to 180)"
    with pytest.raises(ConfigError, match=rf"config key data\.phi_max_deg: {should}, got {bad}"):
        build(make_cfg([f"data.phi_max_deg={bad}"]))


def test_test_ckpt_must_be_last_or_best(make_cfg):
    from rotlearn.cli.train import train

    cfg = make_cfg(["data=tiny", "trainer.fast_dev_run=true", "test_ckpt=middle"])
    with pytest.raises(ConfigError, match="test_ckpt"):
        train(cfg)


def test_calibrate_defaults_to_auto_and_adds_the_calibration(make_cfg):
    from rotlearn.lit import PostHocCalibration

    def scaling(trainer: Trainer) -> list[Callback]:
        return [cb for cb in trainer.callbacks if isinstance(cb, PostHocCalibration)]

    cfg = make_cfg(["data=tiny"])
    assert cfg.calibrate == "auto"
    assert len(scaling(build(cfg)[2])) == 1  # the A head has a belief
    assert not scaling(build(make_cfg(["data=tiny", "calibrate=false"]))[2])
    on = make_cfg(["data=tiny", "calibrate=true"])
    assert on.calibrate is True and len(scaling(build(on)[2])) == 1
    with pytest.raises(ConfigError, match="config key calibrate"):
        build(make_cfg(["data=tiny", "calibrate=[1]"]))


def test_the_a_head_uses_the_auto_solver_and_jacobi_and_eigh_stay_selectable(make_cfg):
    heads = {
        solver: instantiate(make_cfg([] if solver == "auto" else [f"rep.solver={solver}"]).rep)
        for solver in ("auto", "jacobi", "eigh")
    }
    assert {name: head.solver for name, head in heads.items()} == {
        "auto": "auto",
        "jacobi": "jacobi",
        "eigh": "eigh",
    }
    raw = torch.randn(64, 10, dtype=torch.float64)
    for head in heads.values():
        assert torch.allclose(head(raw).R, heads["eigh"](raw).R, atol=1e-9)
    raw = torch.zeros(
        3, 10, dtype=torch.float64, requires_grad=True
    )  # A = 0: all eigenvalues equal
    for head in heads.values():
        head(raw).R.sum().backward()
        assert torch.isfinite(raw.grad).all()


def test_a_checkpoints_solver_fast_loads_as_auto_with_a_warning(make_cfg):
    with pytest.warns(DeprecationWarning, match="rep.solver=fast is deprecated.*rep.solver=auto"):
        head = instantiate(make_cfg(["rep.solver=fast"]).rep)
    assert head.solver == "auto"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["rep.solver=qr"], r"rep\.solver: must be one of auto, jacobi, eigh, got 'qr'"),
        (["rep=quat", "rep.solver=jacobi"], r"rep\.solver: only the 'a' head has a solver"),
    ],
)
def test_bad_solver_choices_name_the_key(make_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message):
        build(make_cfg(overrides))


def test_configs_hold_only_what_differs_from_the_constructors_defaults():
    """A component's YAML starts from its schema (`/schema/<target>` in its defaults list, read
    from the constructor) and repeats no default of it; the store knows every schema."""
    from hydra.core.config_store import ConfigStore

    register_schemas()
    store = ConfigStore.instance()
    for path in sorted(CONFIG_DIR.glob("*/*.yaml")):
        raw = OmegaConf.load(path)
        group = path.parent.name
        node = raw.get(group, raw) if path.read_text().startswith("# @package") else raw
        listed = [str(d).split("@")[0] for d in raw.get("defaults", [])]
        schemas = [d.removeprefix("/schema/") for d in listed if d.startswith("/schema/")]
        if not schemas:
            continue
        (target,) = schemas
        assert store.load(f"schema/{target}.yaml") is not None, path
        assert get_object(node.get("_target_", target)) is get_object(target), path
        defaults = schema(target)
        for key, value in OmegaConf.to_container(node).items():
            if key in ("_target_", "defaults") or key not in defaults:
                continue
            assert (isinstance(value, str) and "${" in value) or value != defaults[key], (
                f"{path.name}: {key}={value!r} repeats the constructor's default"
            )
    assert {f"schema/{t}.yaml" for t in marked()} <= {
        f"schema/{name}" for name in store.list("schema")
    }


def _comment_commands() -> list[tuple[str, list[str]]]:
    """(file, arguments) of each `rotlearn-train` example in conf/'s comments that can run as
    written (no `<placeholder>`, no `...`, no continued line); words after two spaces are
    the comment's own (`(5 seeds)`, `then rotlearn-report ...`)."""
    import re
    import shlex

    found = []
    for path in sorted(CONFIG_DIR.rglob("*.yaml")):
        for line in path.read_text().splitlines():
            match = re.match(r"#\s+(?:.*&&\s*)?rotlearn-train (\S.*?)(?:\s{2,}.*)?$", line)
            if match and not re.search(r"<|\.\.\.|\\$", match[1]):
                found.append((str(path.relative_to(CONFIG_DIR)), shlex.split(match[1])))
    return found


@pytest.mark.parametrize(("where", "args"), _comment_commands(), ids=lambda v: str(v))
def test_every_command_in_a_config_comment_composes_and_validates(
    where, args, tmp_path, monkeypatch
):
    """A config's comment shows how to run it: that command composes (its sweep with the first
    value of each swept key) and validates, the data folders laid out empty. conf/sweep's
    `hydra.sweeper.params.trial='range(0,5)'` reached Hydra unquoted and was refused as a sweep
    of Hydra's own settings."""
    from rotlearn.config import command_line_config
    from tests.conftest import make_data_layout

    monkeypatch.chdir(tmp_path)
    cfg, _ = command_line_config(args, str(tmp_path / "run"))
    make_data_layout(cfg)
    validate(cfg)


@pytest.mark.parametrize("config_name", ["train", "eval"])
def test_the_run_log_writes_a_name_that_is_not_utf8_escaped(config_name, tmp_path, capsys):
    """A received dataset's or run's file name that is not UTF-8 (a surrogate escape) made the
    run log's handler print "--- Logging error ---" and two tracebacks."""
    import logging
    import logging.config

    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = hydra_compose(config_name, return_hydra_config=True)
    job_logging = OmegaConf.to_container(cfg.hydra.job_logging)
    file = {**job_logging["handlers"]["file"], "filename": str(tmp_path / "run.log")}
    logger = logging.getLogger("rotlearn_log_test")  # the run log's handler, on a logger alone
    alone = {"handlers": ["file"], "propagate": False}  # not to pytest's capture either
    logging.config.dictConfig({"version": 1, "disable_existing_loggers": False,
                               "formatters": job_logging["formatters"], "handlers": {"file": file},
                               "loggers": {logger.name: alone}})  # fmt: skip
    try:
        logger.error("%s: refused", "evil\udcff")
    finally:
        for handler in logger.handlers:
            handler.close()
        logger.handlers.clear()
    assert "Logging error" not in capsys.readouterr().err
    assert "evil\\udcff: refused" in (tmp_path / "run.log").read_text()


def test_only_the_arguments_that_needed_a_plus_get_one(tmp_path):
    """A resume replays a run's saved `+optim.amsgrad=true` before the command line's own
    `optim.amsgrad=true`: the `+` went to every argument whose text matched one that had it, so
    the key was appended twice, which Hydra refuses (the resume: "the overrides do not
    compose"). Each argument keeps its own, a sweep's too."""
    from rotlearn.config import command_line_config

    args = ["+optim.amsgrad=true", "optim.amsgrad=true"]
    cfg, argv = command_line_config(args, str(tmp_path / "run"), appendable=args[1:])
    assert argv == args and cfg.optim.amsgrad is True
    sweep = ["-m", "optim.amsgrad=true,false", "seed=1"]
    _, argv = command_line_config(sweep, str(tmp_path / "run"))
    assert argv == ["-m", "+optim.amsgrad=true,false", "seed=1"]
