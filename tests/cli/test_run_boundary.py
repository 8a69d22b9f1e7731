"""A run directory is a sealed box (issue 22): a received run cannot make rotlearn write, delete or
hang outside it, and nothing finished is written again.

Each test copies the session's finished run (`finished_run`) into `<tmp>/work/outputs/runs/<name>`
as someone might send it, crafts one file in it, and runs the command on it. Beside the run lies a
sentinel tree (`<tmp>/home`: a victim file, another run's checkpoint); every test asserts that
nothing outside the run changed or appeared (hashes of everything below `<tmp>` but the run), that
a refused command left the run byte-identical, the message and the exit code (a `SystemExit`
with a message exits 1), and a time bound where the landed code used to hang.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
import torch
import yaml

from rotlearn.cli.resume import plan_resume
from tests.conftest import ONE_EPOCH_RUN, copy_run, run_cli, start_cli, tree_hashes, within

NAME = "2026-01-01_00-00-00-000000"


class Received:
    """A received run and the sentinel tree beside it (module docstring)."""

    def __init__(self, tmp_path: Path, finished_run: Path, resumable: bool = True) -> None:
        self.root = tmp_path
        self.work = tmp_path / "work"
        self.runs = self.work / "outputs" / "runs"
        self.run = copy_run(finished_run, self.runs / NAME, resumable)
        self.home = tmp_path / "home"
        self.victim = self.home / "victim" / "important.txt"
        self.victim.parent.mkdir(parents=True)
        self.victim.write_text("precious\n")
        self.other = self.home / "other_run" / "checkpoints" / "last.ckpt"
        self.other.parent.mkdir(parents=True)
        self.other.write_bytes((finished_run / "checkpoints" / "last.ckpt").read_bytes())
        self.snapshot()

    def snapshot(self) -> None:
        """Hashes to compare with: take them after crafting the run."""
        self.outside = tree_hashes(self.root, skip=self.run)
        self.inside = tree_hashes(self.run)

    def assert_outside_unchanged(self) -> None:
        assert self.victim.read_text() == "precious\n"
        assert tree_hashes(self.root, skip=self.run) == self.outside, "outside the run changed"

    def assert_unchanged(self) -> None:
        self.assert_outside_unchanged()
        assert tree_hashes(self.run) == self.inside, "the refused command changed the run"

    @property
    def ckpt(self) -> Path:
        return self.run / "checkpoints" / "last.ckpt"

    def edit_best_state(self, edit) -> None:
        """Apply `edit(state)` to the state of last.ckpt's best-checkpoint callback."""
        checkpoint = torch.load(self.ckpt, weights_only=True)
        states = checkpoint["callbacks"]
        key = next(k for k, v in states.items() if isinstance(v, dict) and v.get("monitor"))
        edit(states[key])
        torch.save(checkpoint, self.ckpt)

    def add_overrides(self, *lines: str) -> None:
        path = self.run / ".hydra" / "overrides.yaml"
        overrides = yaml.safe_load(path.read_text()) + list(lines)
        path.write_text(yaml.safe_dump(overrides))

    def plan(self, *argv: str):
        return plan_resume([f"ckpt_path={self.run}", "trainer.max_epochs=2", *argv], self.runs)


@pytest.fixture
def received(tmp_path, finished_run, monkeypatch) -> Received:
    monkeypatch.chdir(tmp_path)
    return Received(tmp_path, finished_run)


def refused(received: Received, *argv: str, seconds: float = 60) -> str:
    """The one-line message a resume of the received run is refused with (before Hydra)."""
    with within(seconds), pytest.raises(SystemExit) as info:
        received.plan(*argv)
    message = str(info.value.code)
    assert message.startswith("rotlearn-train: ") and "\n" not in message, message
    received.assert_unchanged()
    return message


# ---- 1. paths in a loaded checkpoint state ------------------------------------------------------

STATE_ATTACKS = {
    # the issue's reproduction: `..` through the checkpoint folder, dirpath removed
    "best_model_path via ..": lambda r, s: (
        s.update(best_model_path=f"{r.run}/checkpoints/../../../../../home/victim/important.txt"),
        s.pop("dirpath"),
    ),
    "kth_best_model_path": lambda r, s: s.update(kth_best_model_path=str(r.victim)),
    "last_model_path": lambda r, s: s.update(last_model_path=str(r.victim)),
    "a best_k_models key": lambda r, s: s.update(best_k_models={str(r.victim): torch.tensor(1.0)}),
    "a folder (rm -r)": lambda r, s: s.update(best_model_path=str(r.victim.parent)),
    "another run's last.ckpt": lambda r, s: s.update(best_model_path=str(r.other)),
    # rebased into the run it would name last.ckpt, which this (best) callback would delete
    "another callback's file": lambda r, s: s.update(
        dirpath=str(r.home / "victim"), best_model_path=str(r.home / "victim" / "last.ckpt")
    ),
    "a remote file system": lambda r, s: s.update(best_model_path="s3://bucket/best.ckpt"),
    "a run file that is not a checkpoint": lambda r, s: s.update(
        best_model_path=s["dirpath"] + "/../.hydra/config.yaml"
    ),
}


@pytest.mark.parametrize("attack", sorted(STATE_ATTACKS))
def test_a_checkpoint_state_naming_files_outside_its_folder_is_refused(received, attack):
    received.edit_best_state(lambda state: STATE_ATTACKS[attack](received, state))
    received.snapshot()
    message = refused(received)
    assert f"refusing to resume {received.run}" in message
    assert str(received.ckpt) in message and "ModelCheckpoint state" in message


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (lambda o: o["state"][0].update(exp_avg=torch.zeros(7)),
         r"optimizer_states\[0\]\.state\[0\]\.exp_avg is of shape \(7,\), not its parameter's"),
        (lambda o: o["param_groups"][0]["params"].pop(),
         r"optimizer_states\[0\] numbers \d+ parameters; the model has \d+"),
    ],
)  # fmt: skip
def test_an_optimizer_state_that_does_not_fit_the_model_is_refused(received, edit, said):
    """An Adam state of the wrong shape failed at the first training step, with a traceback,
    after the resume had moved the run's records and marked it FAILED."""
    checkpoint = torch.load(received.ckpt, weights_only=True)
    edit(checkpoint["optimizer_states"][0])
    torch.save(checkpoint, received.ckpt)
    received.snapshot()
    assert re.search(said, refused(received))


def test_the_issue_reproduction_from_the_command_line_deletes_nothing(received):
    """`rotlearn-train ckpt_path=<run> trainer.max_epochs=3` on the crafted run: exit code 1,
    one line on stderr, the victim and the run untouched."""
    received.edit_best_state(lambda s: STATE_ATTACKS["best_model_path via .."](received, s))
    received.snapshot()
    start = time.monotonic()
    done = run_cli([f"ckpt_path={received.run}", "trainer.max_epochs=3"], received.work)
    assert time.monotonic() - start < 120
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "best_model_path" in lines[0] and "Traceback" not in done.stderr
    received.assert_unchanged()


def test_the_guard_refuses_a_state_while_lightning_restores_it(received, make_cfg):
    """Behind the check before Hydra: the trainer's own guard (`CheckpointStateGuard`) refuses
    the state while the checkpoint is restored, before any callback holds its paths."""
    from rotlearn.checkpoint import UnsafeCheckpointError
    from rotlearn.cli.train import train

    received.edit_best_state(lambda s: STATE_ATTACKS["best_model_path via .."](received, s))
    received.snapshot()
    cfg = make_cfg([*ONE_EPOCH_RUN, "trainer.max_epochs=2", f"ckpt_path={received.ckpt}"],
                   run_dir=received.run)  # fmt: skip
    with pytest.raises(UnsafeCheckpointError, match="best_model_path"):
        train(cfg)
    received.assert_outside_unchanged()
    assert not (received.run / "metrics.json").exists()


def test_a_copied_run_resumes_with_its_checkpoint_paths_moved_into_it(received):
    """A genuine copy: its checkpoint states name the folder it was trained in; they are
    rebased into the copy (no refusal), and the plan names the copy's own files."""
    from rotlearn.checkpoint import load_checkpoint
    from rotlearn.lit.boundary import checked_checkpoint_states

    plan = received.plan()
    assert plan is not None and plan.run_dir == received.run.resolve()
    checkpoint = load_checkpoint(received.ckpt)
    from lightning.pytorch.callbacks import ModelCheckpoint

    callback = ModelCheckpoint(dirpath=received.run / "checkpoints", monitor="val/err_mean",
                               filename="best", auto_insert_metric_name=False)  # fmt: skip
    checked_checkpoint_states(checkpoint, [callback], received.run, received.ckpt)
    state = checkpoint["callbacks"][callback.state_key]
    assert state["best_model_path"] == str(received.run / "checkpoints" / "best.ckpt")
    received.assert_unchanged()


# ---- 2. paths in the replayed overrides ---------------------------------------------------------

OVERRIDE_ATTACKS = {
    "callbacks.last_checkpoint.dirpath=HOME/other_run/checkpoints": (
        "callbacks.last_checkpoint.dirpath"
    ),
    "logger.csv.save_dir=HOME/logs": "logger.csv.save_dir",
    "logger.csv.name=../../../../../home/logs": "logger.csv.name",
    "trainer.default_root_dir=HOME/root": "trainer.default_root_dir",
    "paths.output_dir=HOME/elsewhere": "paths.output_dir",
    "callbacks.checkpoint.filename=../../../../../home/victim/important": (
        "callbacks.checkpoint.filename"
    ),
    "+callbacks.extra={_target_:lightning.pytorch.callbacks.ModelCheckpoint,dirpath:HOME/c}": (
        "callbacks.extra.dirpath"
    ),
    # no dirpath: Lightning puts the file name below the logger's or the run's folder
    "+callbacks.extra={_target_:lightning.pytorch.callbacks.ModelCheckpoint,"
    "filename:../../../../../home/victim/important}": "callbacks.extra.filename",
    # another logger class (the config's schema allows no `paths.*` key but output_dir)
    "+logger.tb={_target_:rotlearn.lit.TensorBoardRunLogger,save_dir:HOME/tb,name:x}": (
        "logger.tb.save_dir"
    ),
    # Lightning formats a file name's `{name}` as `name=<value>`: a path once formatted
    "callbacks.last_checkpoint.filename='{HOME/victim/important}'": (
        "callbacks.last_checkpoint.filename"
    ),
    "callbacks.checkpoint.filename='{../../../../../home/victim/important}'": (
        "callbacks.checkpoint.filename"
    ),
}


@pytest.mark.parametrize("override", sorted(OVERRIDE_ATTACKS))
def test_replayed_overrides_that_write_outside_the_run_are_refused(received, override):
    received.add_overrides(override.replace("HOME", str(received.home)))
    received.snapshot()
    message = refused(received)
    assert (OVERRIDE_ATTACKS[override] in message and "outside the run" in message) or (
        "paths.output_dir" in message and "own directory" in message
    ), message


def test_a_folder_passed_by_position_is_refused(received):
    """A review's reproduction: a checkpoint callback given a folder out of the run by position
    (`_args_`), which the checks by key name did not see, saving `last.ckpt` as a link: the
    resume deleted a folder of that name there (Lightning removes it itself) and wrote
    checkpoints beside it."""
    received.add_overrides(
        "+callbacks.extra={_target_:lightning.pytorch.callbacks.ModelCheckpoint,"
        f"_args_:[{received.home}/c],save_last:link,every_n_train_steps:1}}"
    )
    received.snapshot()
    message = refused(received)
    assert "callbacks.extra._args_: positional arguments are not taken from a file" in message


def test_a_folder_reached_by_dropping_a_link_and_its_dotdot_is_outside(received):
    """Lightning normalises `default_root_dir` (the OOD tables' folder): `x/..` is dropped
    whatever `x` links to, so a path that resolves inside the run through a link deep into it
    was written outside it."""
    (received.run / "a" / "a" / "a" / "a" / "a" / "a").mkdir(parents=True)
    (received.run / "x").symlink_to("a/a/a/a/a/a")
    path = f"{received.run}/x/{'../' * 5}home/outside"
    received.add_overrides(f"trainer.default_root_dir={path}")
    received.snapshot()
    assert f"resolves to {received.home / 'outside'}, outside the run" in refused(received)


@pytest.mark.parametrize(
    ("key", "value"),
    [("version", "'leak-$HOME'"), ("version", "'$ROTLEARN_UNSET_VARIABLE'"), ("save_dir", "'~/x'")],
)
def test_a_path_that_lightning_expands_is_refused(received, key, value):
    """Lightning expands `$VAR` in a logger's folder and a leading `~`: a received run's
    `version='leak-$SECRET'` wrote the resuming user's secret into a folder name."""
    received.add_overrides(f"logger.csv.{key}={value}")
    received.snapshot()
    message = refused(received)
    assert f"logger.csv.{key}" in message and "which Lightning expands" in message


def test_a_file_the_saved_overrides_name_is_opened_only_if_the_command_line_names_it(make_cfg):
    """A received KITTI run's saved `callbacks.ood.autoencoder_ckpt=<path>` made its resume load
    that checkpoint, outside the run, and write its scores into ood.csv (rotlearn-eval already
    took the key from its own command line only)."""
    from rotlearn.cli.resume import _refuse_files_to_open
    from rotlearn.errors import ConfigError

    ae = "/elsewhere/ae/checkpoints/last.ckpt"
    cfg = make_cfg(["data=kitti", "data.root=/data", "callbacks=ood",
                    f"callbacks.ood.autoencoder_ckpt={ae}"])  # fmt: skip
    with pytest.raises(ConfigError, match=rf"autoencoder_ckpt: the run's saved overrides name "
                       rf"{ae}; a resume opens a file they name only when your command line "
                       rf"names it"):  # fmt: skip
        _refuse_files_to_open(cfg, ["trainer.max_epochs=2"])
    _refuse_files_to_open(cfg, [f"callbacks.ood.autoencoder_ckpt={ae}"])
    _refuse_files_to_open(make_cfg(["data=kitti", "data.root=/data", "callbacks=ood"]), [])


@pytest.mark.parametrize("devices", ["4096", "'4096'", "[0,1,2,3,4,5,6,7,8]"])
def test_saved_overrides_do_not_choose_the_processes_or_devices(received, devices):
    """A received run's `trainer.devices=4096` made its resume start 4096 processes (on a CPU
    each device is one, importing torch). A resume takes the machine's keys from its own command
    line only, whatever value the saved overrides give, in any form Lightning reads."""
    received.add_overrides(f"trainer.devices={devices}")
    received.snapshot()
    message = refused(received)
    saved = f"trainer.devices={devices}"
    assert "trainer.devices: how many processes and devices a resume uses is" in message
    assert f"your command line only: {shlex.quote(saved)} to use it again (from " in message
    assert message.endswith(f"overrides.yaml: {saved!r})")  # the saved override, not trainer=cpu
    assert received.plan("trainer.devices=1") is not None  # the user's own value, another one


def test_every_saved_machine_key_is_named_once_with_its_last_value(received):
    """A resumed run's saved overrides hold its earlier values too (the first resume's
    `trainer.devices=2` after the start's `4096`): one refusal names every machine key the
    command line does not set, each at its last value; a key the YAML lacks was saved with `+`
    (the refusal's own suggestion, and the saved text, failed: Hydra refuses to append twice),
    and the command line's value replaces the saved one."""
    received.add_overrides("trainer.devices=4096", "trainer.devices=2", "+trainer.num_nodes=1")
    received.snapshot()
    message = refused(received)
    assert "your command line only: trainer.devices=2 trainer.num_nodes=1 to use them again" in (
        message
    )
    plan = received.plan("trainer.devices=2", "trainer.num_nodes=1")
    keys = [a.lstrip("+").partition("=")[0] for a in plan.args]
    assert keys.count("trainer.num_nodes") == keys.count("trainer.devices") == 1  # the typed


def test_saved_loader_processes_are_the_command_lines_too(make_cfg):
    """The image datasets' `data.num_workers`, as `trainer.devices` (above); the values of
    rotlearn's own configs are not refused, and the resume command a stopped run prints names
    the machine's keys its command line set."""
    from rotlearn.cli.resume import _refuse_machine_keys
    from rotlearn.cli.rundir import keys_to_give_again
    from rotlearn.errors import ConfigError

    cfg = make_cfg(["data=kitti", "data.root=/data", "data.num_workers=64"])
    saved = ["data=kitti", "data.root=/data", "data.num_workers=64"]
    with pytest.raises(ConfigError, match=r"data.num_workers: how many processes .* your command "
                       r"line only: data.num_workers=64 to use it again"):  # fmt: skip
        _refuse_machine_keys(saved, [])
    _refuse_machine_keys(saved, ["data.num_workers=2"])  # the user's own value
    paper_scale = make_cfg(["experiment=kitti_ood_paper_scale", "data.root=/data"])
    assert paper_scale.data.num_workers == 8  # rotlearn's own config asks for them
    _refuse_machine_keys(["experiment=kitti_ood_paper_scale", "data.root=/data"], [])
    assert keys_to_give_again(cfg, saved) == ["data.num_workers=64"]
    assert keys_to_give_again(paper_scale, ["experiment=kitti_ood_paper_scale"]) == []


def test_a_file_with_a_second_name_inside_the_run_is_no_hard_link_out(received):
    """A resume killed while keeping the earlier records leaves them with a second name in a
    hidden history folder (`keep_earlier_records`): that run still resumes."""
    partial = received.run / "history" / ".1.partial"
    partial.mkdir(parents=True)
    os.link(received.run / "status.json", partial / "status.json")
    assert received.plan() is not None


def test_the_users_own_command_line_may_write_elsewhere(received):
    plan = received.plan(f"trainer.default_root_dir={received.home / 'root'}")
    assert plan is not None and f"trainer.default_root_dir={received.home / 'root'}" in plan.args
    received.assert_unchanged()


def test_a_dataset_cache_outside_the_run_is_a_write_outside_it(make_cfg, tmp_path):
    from rotlearn.cli.rundir import check_placement
    from rotlearn.errors import ConfigError

    run = tmp_path / "run"
    cfg = make_cfg(["data=kitti", f"data.root={tmp_path / 'data'}",
                    f"data.cache_dir={tmp_path / 'cache'}"], run_dir=run)  # fmt: skip
    with pytest.raises(ConfigError, match=r"data\.cache_dir: .* outside the run"):
        check_placement(cfg, run)
    check_placement(cfg, run, trusted={"data.cache_dir"})  # set on the user's command line


# ---- 3. what a run directory may hold -----------------------------------------------------------


def _fifo(path: Path) -> None:
    path.unlink(missing_ok=True)
    os.mkfifo(path)


TREE_ATTACKS = {
    "status.json is a named pipe": (lambda r: _fifo(r.run / "status.json"), "FIFO"),
    "csv/metrics.csv is a named pipe": (lambda r: _fifo(r.run / "csv" / "metrics.csv"), "FIFO"),
    ".hydra/config.yaml links to /dev/zero": (
        lambda r: (
            (r.run / ".hydra" / "config.yaml").unlink(),
            (r.run / ".hydra" / "config.yaml").symlink_to("/dev/zero"),
        ),
        "a symlink to /dev/zero",
    ),
    "checkpoints/best.ckpt links outside": (
        lambda r: (
            (r.run / "checkpoints" / "best.ckpt").unlink(),
            (r.run / "checkpoints" / "best.ckpt").symlink_to(r.victim),
        ),
        "outside the run",
    ),
    "status.json nested 100k deep": (
        lambda r: (r.run / "status.json").write_text("[" * 100_000 + "]" * 100_000),
        "status.json: JSON nested too deeply",
    ),
    "status.json is a list": (
        lambda r: (r.run / "status.json").write_text('["COMPLETED"]'),
        "status.json: not a JSON object (a list)",
    ),
    "status.json of 20 MB": (
        lambda r: (r.run / "status.json").write_text(" " * 20_000_000 + "{}"),
        "status.json: too large",
    ),
    "overrides.yaml of 20 MB": (
        lambda r: (r.run / ".hydra" / "overrides.yaml").write_text("- a=1\n" * 3_500_000),
        "overrides.yaml: too large",
    ),
    "overrides.yaml an alias bomb": (
        lambda r: (r.run / ".hydra" / "overrides.yaml").write_text(
            "a: &a [x, x, x, x, x, x, x, x, x]\n"
            + "".join(
                f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
                for p, c in zip("abcdefgh", "bcdefghi", strict=True)
            )
        ),
        "alias",
    ),
    ".hydra/config.yaml a hard link to a file outside": (
        lambda r: (
            (r.run / ".hydra" / "config.yaml").unlink(),
            os.link(r.victim, r.run / ".hydra" / "config.yaml"),
        ),
        "a hard link to a file outside the run (2 names)",
    ),
    "folders 40 deep": (
        lambda r: (r.run / Path(*["d"] * 40)).mkdir(parents=True),
        "folders nested more than 32 deep",
    ),
    "a truncated last.ckpt": (
        lambda r: r.ckpt.write_bytes(r.ckpt.read_bytes()[:50_000]),
        "last.ckpt is not a whole PyTorch checkpoint",
    ),
    "a deflate bomb for last.ckpt": (lambda r: _deflate_bomb(r.ckpt), "would decompress to"),
}


def _deflate_bomb(path: Path) -> None:
    """A zip whose one record inflates 1000-fold (torch would allocate all of it)."""
    path.unlink()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("archive/data.pkl", b"\0" * 64_000_000)


@pytest.mark.parametrize("attack", sorted(TREE_ATTACKS))
def test_a_run_holding_hostile_files_is_refused_quickly_naming_them(received, attack):
    craft, expected = TREE_ATTACKS[attack]
    craft(received)
    received.snapshot()
    message = refused(received, seconds=20)  # several of these used to hang or fill memory
    assert expected in message, message


def test_ckpt_path_last_skips_runs_it_cannot_resume_and_says_so(received, capsys):
    """Newer runs with a named pipe as status.json, or a truncated last.ckpt, are passed over
    quickly (they used to hang `ckpt_path=last`, or be picked and fail), each named."""
    fifo = copy_run(received.run, received.runs / "2026-01-03_00-00-00-000000")
    _fifo(fifo / "status.json")
    truncated = copy_run(received.run, received.runs / "2026-01-02_00-00-00-000000")
    ckpt = truncated / "checkpoints" / "last.ckpt"
    ckpt.write_bytes(ckpt.read_bytes()[:50_000])
    received.snapshot()
    with within(30):
        plan = plan_resume(["ckpt_path=last"], received.runs)
    assert plan.run_dir == received.run.resolve()
    said = capsys.readouterr().err
    assert f"resuming {received.run}" in said
    assert f"skipped {fifo}" in said and "FIFO" in said
    assert f"skipped {truncated}" in said and "not a whole PyTorch checkpoint" in said


# ---- 4. records are written once ------------------------------------------------------------


def _main(monkeypatch, *argv: str, prog: str = "train") -> str:
    """`rotlearn-train` (or `rotlearn-eval`) in this process; the message it exits with."""
    from rotlearn.cli import evaluate, train

    monkeypatch.setattr(sys, "argv", [f"rotlearn-{prog}", *argv])
    with within(60), pytest.raises(SystemExit) as info:
        (train if prog == "train" else evaluate).main()
    return str(info.value.code)


def test_a_new_run_into_a_completed_run_is_refused_before_hydra_writes(
    tmp_path, finished_run, monkeypatch
):
    """The issue's reproduction: `rotlearn-train data=tiny trainer.max_epochs=1 seed=5
    hydra.run.dir=<a COMPLETED run>` left the run saying seed=5 and FAILED."""
    received = Received(tmp_path, finished_run, resumable=False)
    monkeypatch.chdir(received.work)
    message = _main(monkeypatch, "data=tiny", "trainer.max_epochs=1", "seed=5",
                    f"hydra.run.dir={received.run}")  # fmt: skip
    assert f"{received.run} already exists and is not empty" in message
    assert "never writes into an existing directory" in message
    # the hint is a command that works on a finished run (continuing it was refused)
    longer = f"rotlearn-train ckpt_path={received.run} trainer.max_epochs=<more>"
    assert f"(it holds a finished run; to train it longer: {longer})" in message
    received.assert_unchanged()


def test_a_new_run_into_an_unfinished_run_points_to_its_resume(received, monkeypatch):
    monkeypatch.chdir(received.work)
    message = _main(monkeypatch, "data=tiny", f"hydra.run.dir={received.run}")
    assert f"(to continue the run in it: rotlearn-train ckpt_path={received.run})" in message
    received.assert_unchanged()


def test_a_sweep_or_an_evaluation_into_an_existing_directory_is_refused(received, monkeypatch):
    monkeypatch.chdir(received.work)
    message = _main(monkeypatch, "-m", "data=tiny", "seed=1,2",
                    f"hydra.sweep.dir={received.run.parent}")  # fmt: skip
    assert f"{received.run.parent} already exists and is not empty" in message
    message = _main(monkeypatch, f"ckpt={received.run}", f"hydra.run.dir={received.run}",
                    prog="eval")  # fmt: skip
    assert message.startswith("rotlearn-eval: ") and "already exists" in message
    received.assert_unchanged()


@pytest.mark.parametrize("value", ["data.batch_size=0", "data.batches_per_epoch=0",
                                   "data.num_test=0"])  # fmt: skip
def test_a_bad_value_is_refused_before_the_run_directory_exists(tmp_path, monkeypatch, value):
    monkeypatch.chdir(tmp_path)
    message = _main(monkeypatch, "data=tiny", value)
    assert f"config key {value.split('=')[0]}" in message and "nothing was written" in message
    assert list(tmp_path.iterdir()) == []


# ---- 5. a run path with any characters ----------------------------------------------------------


def test_a_run_path_with_any_characters_resumes(tmp_path, finished_run):
    """Quotes, spaces, `=`, `,`, brackets and braces, a backslash, `$`, `%`, non-ASCII letters:
    the run directory is passed to Hydra quoted, so the resume trains and completes."""
    name = "ü é 空 😀 'q' \"d\" a=b,c [x] {y} (z) \\ $HOME %d ~ #"
    runs = tmp_path / "outputs" / "runs"
    run = copy_run(finished_run, runs / name, resumable=True)
    done = run_cli([f"ckpt_path={run}", "trainer.max_epochs=2"], tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((run / "metrics.json").read_text())["epochs"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outputs"]
    assert sorted(p.name for p in runs.iterdir()) == [name]


def test_a_run_path_hydra_cannot_hold_is_refused_in_one_line(tmp_path, finished_run):
    """`${` in a run directory's path: Hydra itself resolves it as an interpolation (its
    `runtime.output_dir`), quoted or not, so the resume is refused, saying why."""
    run = copy_run(finished_run, tmp_path / "runs" / "a ${oc.env:HOME} b", resumable=True)
    with pytest.raises(SystemExit, match=r"rename the folder without '\$\{'"):
        plan_resume([f"ckpt_path={run}", "trainer.max_epochs=2"], tmp_path / "runs")


# ---- 6. two resumes at once -----------------------------------------------------------------


def test_two_resumes_of_one_run_exactly_one_trains(tmp_path, finished_run):
    """The second resume starts while the first trains: it is refused in one line naming the
    first's pid; the first completes; one new history folder, none half-made."""
    run = copy_run(finished_run, tmp_path / "outputs" / "runs" / NAME, resumable=True)
    longer = ["trainer.max_epochs=2", "data.batches_per_epoch=20"]  # seconds of training
    first = start_cli([f"ckpt_path={run}", *longer], tmp_path)
    deadline = time.monotonic() + 120
    lock = run / ".rotlearn.lock"
    while not (lock.is_file() and f'"pid": {first.pid}' in lock.read_text()):
        assert first.poll() is None, first.stderr.read()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    second = subprocess.run(
        [sys.executable, "-m", "rotlearn.train", f"ckpt_path={run}", *longer],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore"},
    )  # fmt: skip
    assert first.poll() is None, "the first resume ended before the second was refused"
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert second.returncode == 1
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and f"in use by pid {first.pid}" in lines[0], second.stderr
    assert sorted(p.name for p in (run / "history").iterdir()) == ["1"]
    assert json.loads((run / "metrics.json").read_text())["epochs"] == 2


# ---- 7. a full disk -------------------------------------------------------------------------


def _private_mounts() -> list[str] | None:
    """The command prefix that gives a private mount namespace where tmpfs can be mounted (as
    root: `unshare -m`; otherwise a user namespace: `unshare -Urm`), or None."""
    if shutil.which("unshare") is None:
        return None
    prefix = ["unshare", "-m"] if os.geteuid() == 0 else ["unshare", "-Urm"]
    probe = subprocess.run([*prefix, "true"], capture_output=True)
    return prefix if probe.returncode == 0 else None


def test_a_full_disk_fails_the_run_and_keeps_the_last_checkpoint(tmp_path, finished_run):
    """Training into a small tmpfs: the first epoch's checkpoints fit, the second's do not. The
    run ends FAILED naming the file and the cause, in one line; last.ckpt stays the first
    epoch's, whole and loadable; no temporary file is left."""
    from rotlearn.checkpoint import load_checkpoint

    prefix = _private_mounts()
    if prefix is None:
        pytest.skip("mounting a tmpfs needs root or a user namespace (unshare); neither works here")
    size = (finished_run / "checkpoints" / "last.ckpt").stat().st_size
    pages = -(-size // 4096) * 4096  # tmpfs allocates whole pages
    kib = (2 * pages + 96 * 1024) // 1024  # two checkpoints and the run's small files, not three
    mnt, out = tmp_path / "mnt", tmp_path / "out"
    mnt.mkdir()
    out.mkdir()
    args = " ".join(f"'{a}'" for a in [*ONE_EPOCH_RUN, "trainer.max_epochs=3"])
    script = (
        f'mount -t tmpfs -o size={kib}k tmpfs "$1" || exit 99\n'
        f'cd "$1" && "{sys.executable}" -m rotlearn.train {args} hydra.run.dir="$1/run" '
        '2> "$2/stderr"\necho $? > "$2/rc"\ncp -a "$1/run" "$2/run"\n'
    )
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore"}
    done = subprocess.run([*prefix, "sh", "-c", script, "sh", str(mnt), str(out)],
                          capture_output=True, text=True, timeout=300, env=env)  # fmt: skip
    if done.returncode == 99:
        pytest.skip(f"tmpfs could not be mounted here: {done.stderr.strip()}")
    stderr = (out / "stderr").read_text()
    assert (out / "rc").read_text().strip() == "1", stderr
    last_line = stderr.strip().splitlines()[-1]
    assert last_line.startswith("rotlearn-train: cannot write ") and ".ckpt" in last_line
    assert "No space left on device" in last_line and "FAILED" in last_line
    run = out / "run"
    status = json.loads((run / "status.json").read_text())
    assert status["status"] == "FAILED" and "No space left on device" in status["error"]
    assert load_checkpoint(run / "checkpoints" / "last.ckpt")["epoch"] == 0
    assert [p.name for p in (run / "checkpoints").iterdir() if p.name.endswith(".tmp")] == []
    assert list(mnt.iterdir()) == []  # the tmpfs was private to the namespace


def _weights(edit):
    def craft(received):
        checkpoint = torch.load(received.ckpt, weights_only=True)
        edit(checkpoint["state_dict"])
        torch.save(checkpoint, received.ckpt)

    return craft


WEIGHT_ATTACKS = {
    "a missing weight": (_weights(lambda w: w.pop(sorted(w)[0])), "missing net."),
    "an extra weight": (_weights(lambda w: w.update(extra=torch.ones(2))), "unexpected extra"),
    "integer weights": (
        _weights(lambda w: w.update({k: v.long() for k, v in w.items()})),
        "is stored as torch.int64; it must be floating point",
    ),
    "another shape": (
        _weights(lambda w: w.update({k: torch.ones(3) for k in sorted(w)[:1]})),
        "is stored with shape (3,)",
    ),
}


@pytest.mark.parametrize("attack", sorted(WEIGHT_ATTACKS))
def test_weights_that_do_not_fit_the_run_are_refused_before_training(received, attack):
    """Lightning's own load would fail midway with a RuntimeError traceback, or cast silently."""
    craft, expected = WEIGHT_ATTACKS[attack]
    craft(received)
    received.snapshot()
    message = refused(received)
    assert expected in message and str(received.ckpt) in message


def test_the_evaluation_never_opens_an_autoencoder_its_checkpoint_names(finished_run, tmp_path):
    """A received run's callbacks.ood.autoencoder_ckpt named a checkpoint outside it, which
    rotlearn-eval opened; only the evaluation's own ood.autoencoder_ckpt is used."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from rotlearn.checkpoint import load_run
    from rotlearn.cli.evaluate import evaluated_config, evaluation_config
    from rotlearn.paths import config_dir

    run = copy_run(finished_run, tmp_path / "run")
    config = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
    config["callbacks"] = {"ood": {"autoencoder_ckpt": "/elsewhere/ae"}}
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    saved = load_run(run)
    OmegaConf.update(saved.config, "callbacks.ood.autoencoder_ckpt", "/elsewhere/ae", merge=True)
    for given, used in (([], None), (["ood.autoencoder_ckpt=mine"], "mine")):
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose("eval", [f"ckpt={run}", f"paths.output_dir={tmp_path}", *given])
        assert evaluation_config(cfg, saved).callbacks.ood.get("autoencoder_ckpt") == used
        recorded = evaluated_config(cfg, saved, members=1)["callbacks"]["ood"]
        # null, not dropped: a report of a run (null by default) and its evaluation labelled
        # the run `callbacks.ood.autoencoder_ckpt=null`, the key being all that differed
        assert "autoencoder_ckpt" in recorded and recorded["autoencoder_ckpt"] == used


def test_an_accelerator_the_machine_lacks_is_refused_for_every_job_and_on_resume(
    received, monkeypatch
):
    """`trainer=gpu` on a CPU machine failed once the run's folder was made: refused before,
    for a sweep's later jobs too (only its first was checked), and on the resume of a received
    run that names one (it moved the run's records into history/, then failed in Lightning).
    TPU: a device no test machine has."""
    monkeypatch.chdir(received.work)
    message = _main(monkeypatch, "-m", "data=tiny", "trainer.accelerator=cpu,tpu",
                    "hydra.sweep.dir=new_sweep")  # fmt: skip
    assert message == (
        "rotlearn-train: config key trainer.accelerator: tpu asks for a device this machine does"
        " not have; on its CPU: trainer=cpu or trainer.accelerator=auto (nothing was written)"
    )
    assert not (received.work / "new_sweep").exists()
    received.add_overrides("trainer.accelerator=tpu")
    received.snapshot()
    assert "config key trainer.accelerator: tpu asks for a device this machine" in refused(received)
