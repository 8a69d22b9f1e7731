"""Files are data, never code: crafted checkpoints and run directories against every loader.

Each payload below runs code, truncates a file or writes one when Hydra instantiates it. Every
loader that rebuilds a model or a run from a file (rotlearn.load, rotlearn-predict, rotlearn-eval,
the OOD evaluation's auto-encoder, resume with ckpt_path) must refuse it with a message naming the
key path (or, in the loggers and training callbacks that no load builds, leave it unread), and
nothing on disk may be created or changed.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import os
import pickle
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import rotlearn
from rotlearn.checkpoint import UnsafeCheckpointError, load_checkpoint
from rotlearn.cli.evaluate import evaluate
from rotlearn.cli.predict import main as predict_main
from rotlearn.cli.resume import resume_arguments
from rotlearn.config import ConfigError
from rotlearn.lit.autoencoder import load_autoencoder
from rotlearn.ood import OODEvaluation
from rotlearn.paths import config_dir
from rotlearn.trust import UntrustedConfigError, check_config, is_trusted_target, trusted_config
from tests.conftest import SMALL_NET, config_options, model_checkpoint


class _Shell:
    """Unpickling this runs `touch <marker>`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class World:
    """A directory an attacker prepared: a victim file, a pickle on disk, and a marker path
    that any executed payload would create."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.marker = root / "pwned"
        self.victim = root / "victim.txt"
        self.victim.write_text("precious\n")
        self.pickle_file = root / "evil.npy.pkl"
        self.pickle_file.write_bytes(pickle.dumps(_Shell(self.marker)))
        self.pickle_text = pickle.dumps(_Shell(self.marker), protocol=0).decode("latin-1")

    def snapshot(self) -> dict[str, str]:
        return {
            str(p.relative_to(self.root)): hashlib.sha256(p.read_bytes()).hexdigest()
            if p.is_file()
            else "dir"
            for p in sorted(self.root.rglob("*"))
        }


# payload name -> (world -> config node); each would act when instantiated
PAYLOADS: dict[str, Callable[[World], object]] = {
    "torch.load of a pickle written by rotlearn.io": lambda w: {
        "_target_": "torch.load",
        "weights_only": False,
        "f": {
            "_target_": "rotlearn.io.write_text_atomic",
            "path": str(w.root / "written.pkl"),
            "text": w.pickle_text,
        },
    },
    "builtins.open truncating a file": lambda w: {
        "_target_": "builtins.open",
        "file": str(w.victim),
        "mode": "w",
    },
    "numpy.load with allow_pickle": lambda w: {
        "_target_": "numpy.load",
        "file": str(w.pickle_file),
        "allow_pickle": True,
    },
    "os.system": lambda w: {"_target_": "os.system", "command": f"touch {w.marker}"},
    "a rotlearn function that writes": lambda w: {
        "_target_": "rotlearn.io.write_text_atomic",
        "path": str(w.victim),
        "text": "gone",
    },
    "an attribute chain through a rotlearn module": lambda w: {
        "_target_": "rotlearn.cli.train.torch.load",
        "f": str(w.pickle_file),
        "weights_only": False,
    },
    "a target that is not a string": lambda w: {"_target_": ["builtins.open"], "file": "x"},
    "an interpolation that decodes into a target": lambda w: (
        "${oc.decode:'{_target_: builtins.open, file: " + str(w.victim) + ", mode: w}'}"
    ),
}

# where in the saved config the payload sits -> the key path the refusal must name
PLACEMENTS = {
    "net": "net",
    "rep.solver": "rep.solver",
    "net._args_.0": "net._args_.0",
    "data.deep.a.b.c": "data.deep.a.b.c",
    "callbacks.ood.items.1": "callbacks.ood.items.1",  # rotlearn-eval reuses callbacks.ood
}


def _expected_key(placement: str, payload: str) -> str:
    """The key path named in the refusal."""
    key = PLACEMENTS[placement]
    return key if payload.startswith("an interpolation") else f"{key}._target_"


def _place(config: dict, placement: str, node: object) -> dict:
    """A copy of `config` with `node` at the dotted `placement` (digits index lists)."""
    config = copy.deepcopy(config)
    parts = placement.split(".")
    here: object = config
    for part, after in itertools.pairwise(parts):
        key = int(part) if isinstance(here, list) else part
        if isinstance(here, dict) and key not in here:
            here[key] = [] if after.isdigit() else {}
        here = here[key]
    if isinstance(here, list):
        here.extend([None] * (int(parts[-1]) + 1 - len(here)))
        here[int(parts[-1])] = node
    else:
        here[parts[-1]] = node
    return config


@pytest.fixture(scope="module")
def genuine_config(tmp_path_factory) -> dict:
    """A real train config, resolved, as a checkpoint stores it."""
    out = tmp_path_factory.mktemp("genuine")
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("train", [f"paths.output_dir={out}", "data=tiny", *SMALL_NET])
    return OmegaConf.to_container(cfg, resolve=True)


@pytest.fixture
def world(tmp_path) -> World:
    return World(tmp_path)


def _checkpoint(world: World, config: dict, name: str = "run") -> Path:
    """A run directory whose checkpoints/last.ckpt carries `config` (plain data only)."""
    ckpt = world.root / name / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    torch.save({"rotlearn_config": config, "state_dict": {}, "epoch": 0}, ckpt)
    return ckpt


def _assert_untouched(world: World, before: dict[str, str]) -> None:
    assert not world.marker.exists(), "a payload ran"
    assert world.victim.read_text() == "precious\n"
    assert world.snapshot() == before, "a file was created or changed"


def _loaders(world: World, ckpt: Path, capsys) -> dict[str, Callable[[], str]]:
    """Each loader, returning the message it refused with."""

    def via_load_file() -> str:
        with pytest.raises(UntrustedConfigError) as info:
            rotlearn.load(ckpt)
        return str(info.value)

    def via_load_dir() -> str:
        with pytest.raises(UntrustedConfigError) as info:
            rotlearn.load(ckpt.parent.parent)
        return str(info.value)

    def via_predict() -> str:
        pairs = world.root / "pairs.txt"
        pairs.write_text("0 0 1 0 0 1\n")
        before = world.snapshot()
        code = predict_main([str(ckpt), str(pairs)])
        assert code == 2
        pairs.unlink()
        assert world.snapshot() == {k: v for k, v in before.items() if k != "pairs.txt"}
        return capsys.readouterr().err

    def via_eval() -> str:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose("eval", [f"ckpt={ckpt}", f"paths.output_dir={world.root / 'eval'}"])
        with pytest.raises(ConfigError) as info:
            evaluate(cfg)
        return str(info.value)

    def via_eval_command_line() -> str:  # its first look at the file, then load_run
        from rotlearn.cli.evaluate import _checked

        with pytest.raises(SystemExit) as info:
            _checked([f"ckpt={ckpt}", f"hydra.run.dir={world.root / 'eval'}"])
        return str(info.value)

    def via_ood_autoencoder() -> str:
        callback = OODEvaluation(autoencoder_ckpt=str(ckpt))
        with pytest.raises(UntrustedConfigError) as info:
            callback._autoencoder(torch.device("cpu"))
        return str(info.value)

    def via_load_autoencoder() -> str:
        with pytest.raises(UntrustedConfigError) as info:
            load_autoencoder(ckpt)
        return str(info.value)

    return {
        "rotlearn.load(file)": via_load_file,
        "rotlearn.load(run dir)": via_load_dir,
        "rotlearn-predict": via_predict,
        "rotlearn-eval": via_eval,
        "rotlearn-eval command line": via_eval_command_line,
        "OOD auto-encoder": via_ood_autoencoder,
        "load_autoencoder": via_load_autoencoder,
    }


LOADERS = [
    "rotlearn.load(file)",
    "rotlearn.load(run dir)",
    "rotlearn-predict",
    "rotlearn-eval",
    "rotlearn-eval command line",
    "OOD auto-encoder",
    "load_autoencoder",
]


@pytest.mark.parametrize("loader", LOADERS)
@pytest.mark.parametrize("payload", sorted(PAYLOADS))
def test_every_loader_refuses_every_payload(world, genuine_config, capsys, loader, payload):
    config = _place(genuine_config, "net", PAYLOADS[payload](world))
    if loader in ("OOD auto-encoder", "load_autoencoder"):
        config["model"]["_target_"] = "rotlearn.lit.AutoEncoderModule"
    ckpt = _checkpoint(world, config)
    before = world.snapshot()
    message = _loaders(world, ckpt, capsys)[loader]()
    assert _expected_key("net", payload) in message
    assert str(ckpt) in message
    _assert_untouched(world, before)


@pytest.mark.parametrize("loader", LOADERS)
@pytest.mark.parametrize("placement", sorted(PLACEMENTS))
def test_nested_payloads_are_found_wherever_they_sit(
    world, genuine_config, capsys, loader, placement
):
    payload = "builtins.open truncating a file"
    config = _place(genuine_config, placement, PAYLOADS[payload](world))
    if loader in ("OOD auto-encoder", "load_autoencoder"):
        config["model"]["_target_"] = "rotlearn.lit.AutoEncoderModule"
    ckpt = _checkpoint(world, config)
    before = world.snapshot()
    message = _loaders(world, ckpt, capsys)[loader]()
    assert _expected_key(placement, payload) in message
    assert "builtins.open" in message
    _assert_untouched(world, before)


@pytest.mark.parametrize("placement", ["logger.tensorboard", "callbacks.mine.items.0"])
@pytest.mark.parametrize("payload", sorted(PAYLOADS))
def test_loggers_and_training_callbacks_are_dropped_unread(
    world, genuine_config, payload, placement
):
    """No load builds a run's loggers or training callbacks: they are left out of the loaded
    config before the gate, so whatever they name is never imported or run, and a run trained
    with a callback of the user's own loads."""
    from rotlearn.checkpoint import load_run

    ckpt = _checkpoint(world, _place(genuine_config, placement, PAYLOADS[payload](world)))
    before = world.snapshot()
    for path in (ckpt, ckpt.parent.parent):
        saved = load_run(path)
        assert "logger" not in saved.config and set(saved.config.callbacks) <= {"ood"}
    _assert_untouched(world, before)


def test_the_payloads_are_real(world):
    """Without the gate, Hydra would run them: the marker appears, the victim is truncated."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    with pytest.raises(InstantiationException, match="magic number"):  # after the unpickling
        instantiate(PAYLOADS["torch.load of a pickle written by rotlearn.io"](world))
    assert world.marker.exists()
    instantiate(PAYLOADS["builtins.open truncating a file"](world)).close()
    assert world.victim.read_text() == ""


# ---- resume: the run directory's saved overrides ----------------------------------------------

OVERRIDE_PAYLOADS = {
    "net._target_=torch.load": "net._target_",
    "+net.f._target_=builtins.open": "net.f._target_",
    "+payload={_target_:builtins.open,file:VICTIM,mode:w}": "payload._target_",
    "rep.solver='${oc.decode:\"{_target_: builtins.open, file: VICTIM, mode: w}\"}'": (
        "reads ${oc.decode:...}"  # a string read as config again: refused before composing
    ),
    "+hydra.callbacks.x._target_=builtins.exec": "hydra.callbacks.x._target_",
    "hydra.searchpath=[file:///tmp]": "hydra.searchpath",
    "rep=quat,sixd": "sweep",
}


def _resumable_run(world: World, overrides_yaml: str, model: tuple = ("data=tiny",)) -> Path:
    """A run whose last.ckpt holds the weights of the model `model` builds (what a resume
    checks), with `overrides_yaml` as its saved overrides."""
    run = world.root / "outputs" / "runs" / "2026-01-01_00-00-00-000000"
    (run / "checkpoints").mkdir(parents=True)
    model_checkpoint(run / "checkpoints" / "last.ckpt", model)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text(overrides_yaml)
    return run


@pytest.mark.parametrize("override", sorted(OVERRIDE_PAYLOADS))
def test_resume_refuses_payloads_in_saved_overrides(world, override):
    line = override.replace("VICTIM", str(world.victim))
    run = _resumable_run(world, f"- data=tiny\n- {OmegaConf.to_yaml([line])[2:]}")
    before = world.snapshot()
    for argv in ([f"ckpt_path={run}"], ["ckpt_path=last"]):
        with pytest.raises(SystemExit) as info:
            resume_arguments(argv, runs_root=run.parent)
        assert OVERRIDE_PAYLOADS[override] in str(info.value), str(info.value)
    _assert_untouched(world, before)


@pytest.mark.parametrize("choice", ["path", "package"])
def test_resume_refuses_saved_overrides_that_load_configs_from_elsewhere(world, choice):
    """Hydra reads `group=<path>` as the YAML file at that path from the group's folder: a
    received run could choose a file of its own as its data config, whose `@package _global_`
    sets Hydra's callbacks (which Hydra builds, past the allowlist); `group@package=option`
    puts a config under such a node. Only an option's name is replayed."""
    run = _resumable_run(world, "")
    notes = run / "notes.yaml"
    payload = {"_target_": "builtins.open", "file": str(world.victim), "mode": "w"}
    body = {
        "data": rotlearn.config.compose(["data=tiny"]).data,
        "hydra": {"callbacks": {"pwn": payload}},
    }
    notes.write_text("# @package _global_\n" + OmegaConf.to_yaml(body))
    where = os.path.relpath(run / "notes", config_dir() / "data")
    saved = {"path": f"data={where}", "package": "+callbacks@hydra.callbacks=ood"}[choice]
    (run / ".hydra" / "overrides.yaml").write_text(f"- data=tiny\n- {saved}\n")
    before = world.snapshot()
    with pytest.raises(SystemExit) as info:
        resume_arguments([f"ckpt_path={run}"], runs_root=run.parent)
    said = str(info.value)
    assert f"override {saved!r}" in said and "overrides.yaml" in said, said
    assert (f"chooses '{where}' for config group data, not an option's name" if choice == "path"
            else "puts config group callbacks under hydra.callbacks") in said  # fmt: skip
    _assert_untouched(world, before)


@pytest.mark.parametrize(
    "text",
    [
        "- !!python/object/apply:os.system ['touch PWNED']\n",
        "net: pointnet\n",
        "- 3\n",
        "- [unclosed\n",
    ],
)
def test_resume_refuses_saved_overrides_that_are_not_a_list_of_strings(world, text):
    run = _resumable_run(world, text.replace("PWNED", str(world.marker)))
    before = world.snapshot()
    with pytest.raises(SystemExit, match=r"overrides\.yaml"):
        resume_arguments([f"ckpt_path={run}"], runs_root=run.parent)
    _assert_untouched(world, before)


def test_resume_command_refuses_a_hostile_run_and_changes_nothing(world):
    """The whole command: rotlearn-train ckpt_path=<run> exits non-zero, writes nothing."""
    payload = f"+payload={{_target_:builtins.open,file:{world.victim},mode:w}}"
    run = _resumable_run(world, f"- {payload}\n")
    before = world.snapshot()
    done = subprocess.run(
        [sys.executable, "-m", "rotlearn.train", f"ckpt_path={run}"],
        cwd=world.root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode != 0
    assert "payload._target_" in done.stderr
    _assert_untouched(world, before)


def test_genuine_saved_overrides_still_resume(world):
    run = _resumable_run(world, "- data=tiny\n- optim.lr=0.001\n- rep=sixd\n", ("rep=sixd",))
    args = resume_arguments([f"ckpt_path={run}"], runs_root=run.parent)
    assert args[:3] == ["data=tiny", "optim.lr=0.001", "rep=sixd"]


# ---- the allowlist itself ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("group", "option"),
    [
        (group, option)
        for group in ("rep", "net", "data", "loss", "optim", "trainer", "logger", "callbacks")
        for option in config_options(group)
    ],
)
def test_every_shipped_config_passes_the_gate(tmp_path, group, option):
    """What rotlearn's own configs build is on the allowlist (a new component must mark itself
    with @config_target, or this fails)."""
    extra = ["data=kitti"] if group == "net" and option != "pointnet" else []
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("train", [f"paths.output_dir={tmp_path}", *extra, f"{group}={option}"])
    trusted = trusted_config(cfg, source="test")
    assert OmegaConf.to_container(trusted) == OmegaConf.to_container(cfg, resolve=True)


def test_the_allowlist_is_exact():
    assert is_trusted_target("rotlearn.heads.make_head")
    assert is_trusted_target("rotlearn.data.KittiOdometryDataModule")
    assert is_trusted_target("torch.optim.Adam")
    assert is_trusted_target("lightning.pytorch.Trainer")
    for target in (
        "rotlearn.io.write_text_atomic",  # rotlearn's, but not a component
        "rotlearn.data.ImagePairDataModule",  # a base class: marks are not inherited
        "rotlearn.nets.PointNet.load_state_dict",
        "rotlearn.cli.train.torch.load",
        "rotlearn.trust.config_target",
        "rotlearn.no_such_module.Thing",
        "torch.optim.Optimizer.__init__",
        "torch.load",
        "builtins.eval",
        "lightning.pytorch.Trainer ",
        "",
        None,
        3,
    ):
        assert not is_trusted_target(target), target


def test_check_config_reports_the_deepest_key_and_depth_bombs(tmp_path):
    nested: dict = {"_target_": "builtins.open"}
    with pytest.raises(UntrustedConfigError, match=r"a\.0\.b\._target_: 'builtins\.open'"):
        check_config({"a": [{"b": nested}]}, source=tmp_path)
    bomb: dict = {}
    for _ in range(100):
        bomb = {"x": bomb}
    with pytest.raises(UntrustedConfigError, match="nested too deeply"):
        check_config(bomb, source=tmp_path)
    with pytest.raises(UntrustedConfigError, match="keys must be strings"):
        check_config({"a": {1: "x"}}, source=tmp_path)


def test_check_config_refuses_arguments_passed_by_position(tmp_path):
    """What a component may write is checked by argument name (a checkpoint callback's
    `dirpath`): a folder given by position went unseen, and a resume wrote there."""
    named = {"_target_": "lightning.pytorch.callbacks.ModelCheckpoint", "dirpath": "/elsewhere"}
    check_config({"callbacks": {"extra": named}}, source=tmp_path)  # its placement: rundir's
    node = {"_target_": "lightning.pytorch.callbacks.ModelCheckpoint", "_args_": ["/elsewhere"]}
    with pytest.raises(UntrustedConfigError, match=r"config key callbacks\.extra\._args_: "
                       r"positional arguments are not taken from a file"):  # fmt: skip
        check_config({"callbacks": {"extra": node}}, source=tmp_path)


# ---- checkpoint files that are not checkpoints ---------------------------------------------


@pytest.mark.parametrize(
    "content",
    [b"hello, I am text\n", b"PK\x03\x04garbage", b"", pickle.dumps([1, 2, 3], protocol=2)],
    ids=["text", "broken zip", "empty", "a pickled list"],
)
def test_a_file_that_is_no_checkpoint_is_refused_without_advice_to_unpickle(tmp_path, content):
    path = tmp_path / "model.ckpt"
    path.write_bytes(content)
    with pytest.raises(UnsafeCheckpointError) as info:
        load_checkpoint(path)
    assert str(path) in str(info.value)
    assert "weights_only=False" not in str(info.value)
    assert "will likely succeed" not in str(info.value)
