"""Resume after SIGKILL: the same run directory, the same final numbers as an uninterrupted run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from rotlearn.cli.train import resume_arguments
from tests.conftest import SMALL_NET

ARGS = [
    "data=tiny",
    "data.batches_per_epoch=25",
    "trainer.max_epochs=6",
    "trainer.enable_progress_bar=false",
    "logger=csv",
    *SMALL_NET,
]


def _train(args: list[str], cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.Popen(
        [sys.executable, "-m", "rotlearn.train", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _checkpoint_epoch(path: Path) -> int:
    try:
        return int(torch.load(path, weights_only=True)["epoch"])
    except (OSError, RuntimeError, EOFError, KeyError):
        return -1  # not there yet


def test_sigkill_then_resume_matches_an_uninterrupted_run(tmp_path):
    run = tmp_path / "run"
    job = _train([*ARGS, f"hydra.run.dir={run}"], tmp_path)
    last = run / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 300
    while _checkpoint_epoch(last) < 1:  # killed after its 2nd checkpoint (epoch index 1)
        assert job.poll() is None, f"training ended before it could be killed: {job.stderr.read()}"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    job.send_signal(signal.SIGKILL)
    job.wait()
    killed_at = _checkpoint_epoch(last)
    assert not (run / "metrics.json").exists() and killed_at < 5, "the run finished before the kill"

    resumed = _train([f"ckpt_path={run}"], tmp_path)
    assert resumed.wait(timeout=300) == 0, resumed.stderr.read()
    reference = _train([*ARGS, f"hydra.run.dir={tmp_path / 'reference'}"], tmp_path)
    assert reference.wait(timeout=300) == 0, reference.stderr.read()

    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics == json.loads((tmp_path / "reference" / "metrics.json").read_text())
    assert metrics["epochs"] == 6
    # one CSV log continues across the kill: every epoch appears, in the original directory
    rows = (run / "csv" / "metrics.csv").read_text()
    assert rows.count("\n") > 6


def _fake_run(root: Path, name: str, overrides: list[str]) -> Path:
    run = root / name
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    return run


def test_resume_arguments_continue_the_run_with_its_own_overrides(tmp_path):
    old = _fake_run(tmp_path, "2026-01-01_00-00-00-000000", ["rep=sixd"])
    new = _fake_run(tmp_path, "2026-01-02_00-00-00-000000", ["rep=quat", "optim.lr=0.001"])
    args = resume_arguments(["ckpt_path=last", "trainer.max_epochs=9"], runs_root=tmp_path)
    assert args == [
        "rep=quat",
        "optim.lr=0.001",
        "trainer.max_epochs=9",
        f"ckpt_path={(new / 'checkpoints' / 'last.ckpt').resolve()}",
        f"hydra.run.dir={new.resolve()}",
    ]
    assert resume_arguments([f"ckpt_path={old}"])[0] == "rep=sixd"
    assert resume_arguments(["rep=a"]) == ["rep=a"]
    assert resume_arguments(["ckpt_path=null"]) == ["ckpt_path=null"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["-m", "ckpt_path=last"], "cannot be used with -m"),
        (["ckpt_path=last"], "no run under"),
        (["ckpt_path=/no/such/run"], "no checkpoint at"),
    ],
)
def test_resume_arguments_refuse_what_cannot_be_resumed(tmp_path, argv, message):
    with pytest.raises(SystemExit, match=message):
        resume_arguments(argv, runs_root=tmp_path)


def test_a_finished_run_is_not_resumed(make_cfg):
    from rotlearn.cli.train import train

    cfg = make_cfg(["data=tiny", "trainer.max_epochs=1", "logger=none", *SMALL_NET])
    train(cfg)
    run = Path(cfg.paths.output_dir)
    again = make_cfg(["data=tiny", "logger=none", *SMALL_NET, f"ckpt_path={run}"], run_dir=run)
    with pytest.raises(FileExistsError, match="finished run"):
        train(again)
