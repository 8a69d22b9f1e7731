"""rotlearn.lit.boundary: a restored checkpoint callback state names only its own files in the
run; the trainer's checkpoint I/O writes durably and deletes only the run's checkpoints."""

from __future__ import annotations

import copy
import errno
import os

import lightning.pytorch as pl
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from rotlearn import io
from rotlearn.checkpoint import UnsafeCheckpointError, load_checkpoint
from rotlearn.io import WriteError
from rotlearn.lit.boundary import RunCheckpointIO, checked_checkpoint_states
from rotlearn.lit.state import rng_states


@pytest.fixture
def run(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (tmp_path / "victim.txt").write_text("precious\n")
    return run


def _best(run) -> ModelCheckpoint:
    return ModelCheckpoint(dirpath=run / "checkpoints", filename="best", monitor="val/err_mean")


def _state(callback, saved_dir: str, **paths) -> dict:
    state = {"monitor": callback.monitor, "best_model_score": torch.tensor(1.0),
             "best_model_path": f"{saved_dir}/best.ckpt", "current_score": torch.tensor(1.0),
             "dirpath": saved_dir, "best_k_models": {f"{saved_dir}/best.ckpt": torch.tensor(1.0)},
             "kth_best_model_path": f"{saved_dir}/best.ckpt", "kth_value": torch.tensor(1.0),
             "last_model_path": ""}  # fmt: skip
    return {"callbacks": {callback.state_key: {**state, **paths}}}


def test_a_moved_runs_paths_are_rebased_into_it(run):
    callback = _best(run)
    checkpoint = _state(callback, "/elsewhere/old_run/checkpoints")
    checked_checkpoint_states(checkpoint, [callback], run, "last.ckpt")
    state = checkpoint["callbacks"][callback.state_key]
    here = str(run.resolve() / "checkpoints")
    assert state["dirpath"] == callback.dirpath == here
    assert state["best_model_path"] == state["kth_best_model_path"] == f"{here}/best.ckpt"
    assert list(state["best_k_models"]) == [f"{here}/best.ckpt"]


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("best_model_path", "{dir}/../../victim.txt"),
        ("best_model_path", "{dir}/../../victim.ckpt"),
        ("best_model_path", "{dir}/last.ckpt"),  # another callback's file
        ("best_model_path", "{dir}/sub/best.ckpt"),
        ("best_model_path", "memory://best.ckpt"),
        ("best_model_path", 7),
        ("kth_best_model_path", "/victim.txt"),
        ("last_model_path", "{dir}/best.ckpt"),  # not a `last` file
        ("best_k_models", {"{dir}/../x.ckpt": 1.0}),
        ("best_k_models", ["{dir}/best.ckpt"]),
        ("best_model_score", "1.0"),
        ("dirpath", 3),
    ],
)
def test_a_state_naming_anything_else_is_refused(run, key, value):
    callback = _best(run)
    saved = "/elsewhere/old/checkpoints"
    fill = lambda v: v.format(dir=saved) if isinstance(v, str) else v  # noqa: E731
    if isinstance(value, dict):
        value = {fill(k): v for k, v in value.items()}
    elif isinstance(value, list):
        value = [fill(v) for v in value]
    checkpoint = _state(callback, saved, **{key: fill(value)})
    with pytest.raises(UnsafeCheckpointError, match=key) as info:
        checked_checkpoint_states(checkpoint, [callback], run, "x/last.ckpt")
    assert "x/last.ckpt" in str(info.value)


def _genuine_training_state() -> dict:
    """The loops', optimizer's and scheduler's states of a checkpoint, as Lightning saves them."""
    model = torch.nn.Linear(2, 2)
    optimizer = torch.optim.Adam(model.parameters())
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, 1)
    trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False)  # fmt: skip
    return {"loops": {"fit_loop": trainer.fit_loop.state_dict()},
            "optimizer_states": [optimizer.state_dict()],
            "lr_schedulers": [scheduler.state_dict()],
            "callbacks": {"EpochLosses": {"losses": []}},
            "rng_states": rng_states()}  # fmt: skip


@pytest.mark.parametrize(
    ("path", "junk", "said"),
    [
        (("callbacks", "EpochLosses"), "junk", "callbacks: the state of EpochLosses must be a"),
        (("loops", "fit_loop", "epoch_progress"), "junk", "loops.fit_loop.epoch_progress must"),
        (("loops",), [1], "loops must be a mapping of loop states down to numbers"),
        (("optimizer_states", 0), "junk", r"optimizer_states\[0\] must be a mapping with state"),
        (("optimizer_states", 0, "param_groups"), {}, r"optimizer_states\[0\] must be"),
        (("lr_schedulers", 0), 3, r"lr_schedulers\[0\] must be a mapping"),
        (("rng_states", "torch"), torch.zeros(3), r"rng_states cannot be restored \(TypeError: "),
        (("rng_states", "python"), [3, [1, 2], None], r"rng_states cannot be restored "),
        (("rng_states",), [], r"rng_states must be a mapping"),
        (("rng_states", "cuda"), [torch.zeros(3)], r"rng_states\.cuda must be a list of byte "),
    ],
)
def test_a_training_state_of_the_wrong_shape_is_refused_before_the_resume(run, path, junk, said):
    """Lightning restores these inside `fit`: a callback state or a loop counter that was text
    gave an AttributeError or TypeError traceback after the resume had moved the run's records
    and marked it FAILED. They are checked with the checkpoint callbacks' states, first."""
    checkpoint = _genuine_training_state()
    checked_checkpoint_states(copy.deepcopy(checkpoint), [_best(run)], run, "last.ckpt")
    node = checkpoint
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = junk
    torch.manual_seed(123)  # this process's state: another than the checkpoint's
    before = torch.get_rng_state()
    with pytest.raises(UnsafeCheckpointError, match=rf"^last\.ckpt: {said}"):
        checked_checkpoint_states(checkpoint, [_best(run)], run, "last.ckpt")
    assert torch.equal(torch.get_rng_state(), before)  # a check restores nothing


def test_a_symlink_resolving_out_of_the_run_is_refused(run, tmp_path):
    (run / "checkpoints" / "best.ckpt").symlink_to(tmp_path / "victim.txt")
    callback = _best(run)
    checkpoint = _state(callback, str(run / "checkpoints"))
    with pytest.raises(UnsafeCheckpointError, match="outside the run"):
        checked_checkpoint_states(checkpoint, [callback], run, "last.ckpt")


def test_a_template_filename_matches_the_files_it_writes(run):
    callback = ModelCheckpoint(dirpath=run / "checkpoints", monitor="val/loss",
                               filename="{epoch}-{val_loss:.2f}")  # fmt: skip
    saved = str(run / "checkpoints")
    ok = _state(callback, saved, best_model_path=f"{saved}/epoch=3-val_loss=0.12-v1.ckpt",
                best_k_models={}, kth_best_model_path="")  # fmt: skip
    checked_checkpoint_states(ok, [callback], run, "last.ckpt")
    bad = _state(callback, saved, best_model_path=f"{saved}/last.ckpt")
    with pytest.raises(UnsafeCheckpointError):
        checked_checkpoint_states(bad, [callback], run, "last.ckpt")


def test_checkpoint_io_deletes_only_the_runs_checkpoint_files(run, tmp_path):
    io_ = RunCheckpointIO(run)
    keep = [tmp_path / "victim.txt", run / "checkpoints", run / "metrics.json"]
    (run / "metrics.json").write_text("{}")
    (tmp_path / "other.ckpt").write_bytes(b"x")
    keep.append(tmp_path / "other.ckpt")
    link = run / "checkpoints" / "link.ckpt"
    link.symlink_to(tmp_path / "victim.txt")
    keep.append(link)
    for path in [*keep, run / "checkpoints" / ".." / ".." / "other.ckpt"]:
        io_.remove_checkpoint(path)
    assert all(os.path.lexists(p) for p in keep)
    own = run / "checkpoints" / "best.ckpt"
    own.write_bytes(b"x")
    io_.remove_checkpoint(own)
    assert not own.exists()


def test_checkpoint_io_keeps_the_previous_checkpoint_when_a_write_fails(run, monkeypatch):
    io_ = RunCheckpointIO(run)
    path = run / "checkpoints" / "last.ckpt"
    io_.save_checkpoint({"epoch": 0, "state_dict": {"w": torch.ones(3)}}, path)
    assert io_.load_checkpoint(path)["epoch"] == 0

    def full_disk(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io.os, "write", full_disk)
    with pytest.raises(WriteError, match=r"last\.ckpt: No space left on device"):
        io_.save_checkpoint({"epoch": 1, "state_dict": {"w": torch.zeros(3)}}, path)
    monkeypatch.undo()
    assert load_checkpoint(path)["epoch"] == 0
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.ckpt"]


@pytest.mark.filterwarnings("ignore:Experiment logs directory .* exists and is not empty")
@pytest.mark.filterwarnings("ignore:Checkpoint directory .* exists and is not empty")  # the link
def test_checkpoint_io_writes_only_inside_the_run_or_a_callbacks_folder(tmp_path):
    """A review's reproduction: a checkpoint callback without a dirpath writes below the
    logger's folder, and a run may hold a link inside it (csv/checkpoints -> ..); its file name
    ../pwned then wrote beside the run. The write is refused; a callback's own folder outside
    the run (a user's dirpath) is written."""
    from lightning.pytorch.loggers import CSVLogger
    from torch.utils.data import DataLoader, TensorDataset

    from tests.lit.test_state import Tiny

    run = tmp_path / "run"
    (run / "csv").mkdir(parents=True)
    (run / "csv" / "checkpoints").symlink_to("..")  # resolves inside the run
    escape = ModelCheckpoint(filename="../pwned")
    data = DataLoader(TensorDataset(torch.randn(8, 2)), batch_size=4)
    trainer = pl.Trainer(max_epochs=1, default_root_dir=run, logger=CSVLogger(run, "csv", ""),
                         callbacks=[escape], plugins=[RunCheckpointIO(run)],
                         enable_progress_bar=False, enable_model_summary=False)  # fmt: skip
    with pytest.raises(UnsafeCheckpointError, match=r"refusing to write .*pwned\.ckpt: it "
                       r"resolves to .*, outside the run"):  # fmt: skip
        trainer.fit(Tiny(), data)
    assert not (tmp_path / "pwned.ckpt").exists()
    elsewhere = tmp_path / "elsewhere"
    given = ModelCheckpoint(dirpath=elsewhere, filename="kept")
    trainer = pl.Trainer(max_epochs=1, default_root_dir=run, logger=False, callbacks=[given],
                         plugins=[RunCheckpointIO(run, [given.dirpath])],
                         enable_progress_bar=False, enable_model_summary=False)  # fmt: skip
    trainer.fit(Tiny(), data)
    assert (elsewhere / "kept.ckpt").is_file()
