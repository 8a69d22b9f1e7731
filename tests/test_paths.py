"""`rotlearn.paths.checkpoint_file`: which checkpoint a command line names, and what a folder
that is no run is instead."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from rotlearn.paths import checkpoint_file


def _run(path: Path) -> Path:
    (path / "checkpoints").mkdir(parents=True)
    (path / "checkpoints" / "last.ckpt").touch()  # looked at, never read
    return path


def test_a_run_directory_names_its_last_checkpoint_and_a_file_itself(tmp_path):
    run = _run(tmp_path / "run")
    assert checkpoint_file(run) == run / "checkpoints" / "last.ckpt"
    assert checkpoint_file(run / "checkpoints" / "last.ckpt") == run / "checkpoints" / "last.ckpt"
    with pytest.raises(FileNotFoundError, match=r"^no checkpoint at .*absent$"):
        checkpoint_file(tmp_path / "absent")


def test_outputs_names_its_runs_and_sweep_jobs_below_it(tmp_path):
    """`ckpt=outputs` said "is not a rotlearn run": its runs lie two and three folders down
    (outputs/runs/<time>, outputs/multirun/<time>/<job>); they are named, runs further down are
    not looked for, and a sweep directory names its own jobs only."""
    outputs = tmp_path / "outputs"
    single = _run(outputs / "runs" / "2026-11-26_10-00-00")
    sweep = outputs / "multirun" / "2026-11-26_11-00-00"
    jobs = [_run(sweep / str(n)) for n in range(2)]
    (sweep / "multirun.yaml").touch()
    _run(outputs / "a" / "b" / "c" / "too deep")
    _run(jobs[0] / "nested")  # a sweep directory's jobs only: one folder down
    shown = ", ".join(map(str, [*jobs, single]))
    with pytest.raises(FileNotFoundError, match=rf"holds runs, not one run: pass one of them, "
                       rf"{re.escape(shown)}$"):  # fmt: skip
        checkpoint_file(outputs)
    with pytest.raises(FileNotFoundError, match=rf"is a sweep directory, not one run: pass one "
                       rf"of its jobs, {re.escape(', '.join(map(str, jobs)))}$"):  # fmt: skip
        checkpoint_file(sweep)


def test_a_folder_of_many_runs_names_eight_and_counts_the_rest(tmp_path):
    runs = [_run(tmp_path / "runs" / f"{n:02}") for n in range(11)]
    with pytest.raises(FileNotFoundError, match=rf"{re.escape(str(runs[7]))} and 3 more$"):
        checkpoint_file(tmp_path)


def test_a_folder_without_runs_says_what_to_pass(tmp_path):
    (tmp_path / "empty" / "x").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"empty is not a rotlearn run: it has no "
                       r"checkpoints/last\.ckpt \(pass a run directory"):  # fmt: skip
        checkpoint_file(tmp_path / "empty")
