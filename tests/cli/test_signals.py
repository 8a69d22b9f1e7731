"""SIGTERM and SIGINT during training leave a record and a resume command; sweeps list every job;
a diverged run says so."""

from __future__ import annotations

import json
import math
import multiprocessing
import re
import signal
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from rotlearn.cli.callbacks import JobStatusCallback, summarise_jobs
from rotlearn.lit import barely_learned, divergence
from rotlearn.report import make_report
from tests.conftest import CONFIG_DIR, RESUMABLE, checkpoint_epoch, start_cli

# --- signals -----------------------------------------------------------------------------------


# about 20 s each on an idle machine (two trainings of 3 short epochs), up to a minute when busy
@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_leaves_an_interrupted_status_and_a_resume_command_that_works(tmp_path, sig, code):
    run = tmp_path / "run"
    job = start_cli([*RESUMABLE, "trainer.max_epochs=3", f"hydra.run.dir={run}"], tmp_path)
    last = run / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 300
    while checkpoint_epoch(last) < 0:  # the first checkpoint (end of epoch 0)
        assert job.poll() is None, f"training ended before the signal: {job.stderr.read()}"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    job.send_signal(sig)
    assert job.wait(timeout=120) == code, job.stderr.read()

    status = json.loads((run / "status.json").read_text())
    assert status["status"] == "INTERRUPTED" and status["signal"] == sig.name
    finished = status["last_finished_epoch"] + 1  # counted from 0 in the record, 1 in the words
    assert status["error"].startswith(f"stopped by {sig.name} after {finished} finished epoch")
    assert status["last_finished_epoch"] == checkpoint_epoch(last) < 2
    assert status["resume_command"] == f"rotlearn-train ckpt_path={run.resolve()}"
    assert not (run / "metrics.json").exists()

    command = status["resume_command"].split()
    assert command[0] == "rotlearn-train"
    resumed = start_cli(command[1:], tmp_path)  # the same arguments, through python -m
    assert resumed.wait(timeout=300) == 0, resumed.stderr.read()
    assert json.loads((run / "status.json").read_text())["status"] == "COMPLETED"
    assert json.loads((run / "metrics.json").read_text())["epochs"] == 3
    earlier = json.loads((run / "history" / "1" / "status.json").read_text())
    assert earlier["status"] == "INTERRUPTED"  # the interrupted attempt's record is kept


@pytest.mark.parametrize(("last", "words"), [(None, "before its first epoch ended, so no "
                                                     "checkpoint holds anything to resume"),
                                              (0, "after 1 finished epoch;"),
                                              (4, "after 5 finished epochs;")])  # fmt: skip
def test_an_interruption_counts_the_epochs_it_finished(tmp_path, last, words):
    """The record keeps Lightning's epoch index (from 0); the message said "after epoch 1" of a
    run that had finished 2, while metrics.json's `epochs` counts from 1."""
    from rotlearn.cli.training import RunInterrupted

    stop = RunInterrupted(tmp_path, "SIGTERM", last, [])
    assert stop.message.startswith(f"stopped by SIGTERM {words}") and stop.code == 143
    assert stop.status["last_finished_epoch"] == last
    # before the first checkpoint no command resumes it (the one printed was refused: no
    # checkpoints/last.ckpt); after it, the message ends in the command
    assert (stop.resume_command is None) == (last is None)
    assert stop.message.endswith("keeps the attempt's log)" if last is None else
                                 f"resume: {stop.resume_command}")  # fmt: skip
    # epochs finished but no last.ckpt that loads (callbacks=none, a damaged one): no command
    # either (the one printed was refused)
    lost = RunInterrupted(tmp_path, "SIGTERM", last, [], resumable=False)
    assert lost.resume_command is None and lost.message.endswith("keeps the attempt's log)")
    if last is not None:
        assert f"{words[6:-1]}, but no checkpoints/last.ckpt loads to resume from" in lost.message


@pytest.mark.parametrize("path", ["outputs/kitti_ae", "outputs/kitti ae 'q' $x"])
def test_the_resume_command_names_again_the_files_the_run_opens(tmp_path, path):
    """A resume opens an auto-encoder checkpoint only when its own command line names it: the
    command a stopped KITTI OOD run printed (`ckpt_path=<run>` alone) was refused. Pasted into
    a shell, the command gives each path as it is: the file's to Hydra, the run's to rotlearn,
    which reads `ckpt_path=` as written, not through Hydra (a run folder named `kitti ae 'q' $x`
    was printed unquoted: the shell split it and expanded `$x`)."""
    import shlex

    from hydra.core.override_parser.overrides_parser import OverridesParser

    from rotlearn.cli.resume import plan_resume
    from rotlearn.cli.rundir import keys_to_give_again
    from rotlearn.cli.training import RunInterrupted

    run = tmp_path / path.rpartition("/")[2]
    config = {"callbacks": {"ood": {"autoencoder_ckpt": path}}, "data": {"num_workers": 3}}
    again = keys_to_give_again(config, ["data.num_workers=3", "+trainer.devices=[0,1]"])
    stop = RunInterrupted(run, "SIGTERM", 0, again)
    words = shlex.split(stop.resume_command)
    assert words[:2] == ["rotlearn-train", f"ckpt_path={run.resolve()}"]
    parsed = OverridesParser.create().parse_overrides(words[2:])
    assert [(o.key_or_group, o.value()) for o in parsed] == [
        ("callbacks.ood.autoencoder_ckpt", path),
        ("data.num_workers", 3),
        ("trainer.devices", [0, 1]),
    ]
    with pytest.raises(SystemExit, match=rf"no checkpoint at '?{re.escape(str(run.resolve()))}"):
        plan_resume(words[1:])  # the resume reads the run's path back as it is
    assert stop.status["resume_command"] == stop.resume_command


# --- sweeps ------------------------------------------------------------------------------------


def _multirun_config(sweep: Path, task_overrides: list[str]):
    """The config a multirun hands its callbacks: composed, with the sweep's overrides set."""
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.sweep.dir = str(sweep)
        cfg.hydra.overrides.task = task_overrides
    return cfg


def _write_job(sweep: Path, num: int, overrides: list[str], status: dict) -> Path:
    job = sweep / str(num)
    (job / ".hydra").mkdir(parents=True)
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", overrides=[*overrides, f"paths.output_dir={job}"])
    OmegaConf.save(cfg, job / ".hydra" / "config.yaml")
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (job / "status.json").write_text(
        json.dumps({"num": num, "dir": str(job), "overrides": overrides, **status})
    )
    return job


def test_a_multirun_lists_every_job_as_pending_before_it_runs(tmp_path):
    sweep = tmp_path / "sweep"
    cfg = _multirun_config(sweep, ["rep=a,sixd", "seed=1,2", "trainer.max_epochs=1"])
    JobStatusCallback().on_multirun_start(cfg)
    summary = json.loads((sweep / "jobs.json").read_text())
    assert summary["pending"] == 4 and summary["completed"] == 0
    assert [job["status"] for job in summary["jobs"]] == ["PENDING"] * 4
    assert [job["overrides"] for job in summary["jobs"]] == [
        [f"rep={rep}", f"seed={seed}", "trainer.max_epochs=1"]
        for rep in ("a", "sixd")
        for seed in (1, 2)
    ]
    assert summary["jobs"][3]["dir"] == str((sweep / "3").resolve())

    _write_job(sweep, 0, summary["jobs"][0]["overrides"], {"status": "COMPLETED"})
    stop = {"status": "INTERRUPTED", "error": "stopped by SIGTERM after epoch 0; resume: X"}
    _write_job(sweep, 1, summary["jobs"][1]["overrides"], stop)
    summary = summarise_jobs(sweep)
    assert [job["status"] for job in summary["jobs"]] == [
        "COMPLETED", "INTERRUPTED", "PENDING", "PENDING"
    ]  # fmt: skip

    report = make_report(sweep)["report"].read_text()
    assert "4 jobs: 0 completed" in report and "2 pending" in report
    assert "| 1 | INTERRUPTED |" in report and "stopped by SIGTERM" in report
    assert "| 2 | PENDING | rep=sixd seed=1 trainer.max_epochs=1 | never ran |" in report
    assert "| 3 | PENDING | rep=sixd seed=2" in report


def test_a_sweep_whose_jobs_are_not_known_ahead_plans_nothing(tmp_path):
    cfg = _multirun_config(tmp_path / "sweep", ["seed=1,2"])
    with open_dict(cfg):
        cfg.hydra.sweeper = {"_target_": "hydra_plugins.hydra_optuna_sweeper.OptunaSweeper"}
    JobStatusCallback().on_multirun_start(cfg)
    assert not (tmp_path / "sweep" / "jobs.json").exists()


def test_a_sweep_job_logs_where_the_sweep_stands_once_at_its_end(tmp_path, caplog):
    """ "sweep so far: ..." was logged twice a job, when it started and when it ended; jobs.json
    still follows the job from its start."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from rotlearn.cli.callbacks import record_job

    sweep = tmp_path / "sweep"
    cfg = _multirun_config(sweep, ["seed=1,2"])
    with open_dict(cfg):
        cfg.hydra.mode = RunMode.MULTIRUN
        cfg.hydra.job.num = 0
    holder = HydraConfig.instance()
    previous, _ = holder.cfg, holder.set_config(cfg)
    try:
        with caplog.at_level("INFO", logger="rotlearn"):
            record_job(sweep / "0", "RUNNING")
            running = json.loads((sweep / "jobs.json").read_text())["running"]
            record_job(sweep / "0", "COMPLETED")
    finally:
        holder.cfg = previous
    assert running == 1
    said = [r.getMessage() for r in caplog.records if "sweep so far" in r.getMessage()]
    assert said == ["sweep so far: 1 completed, 0 failed, 0 interrupted, 0 running, 0 pending"]


def _finish_job(sweep: Path, num: int) -> None:
    job = sweep / str(num)
    job.mkdir()
    (job / "status.json").write_text(json.dumps({"num": num, "status": "COMPLETED"}))
    summarise_jobs(sweep)


def test_parallel_jobs_never_lose_each_others_updates(tmp_path):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "planned_jobs.json").write_text(json.dumps([{"num": n} for n in range(8)]))
    context = multiprocessing.get_context("fork")
    jobs = [context.Process(target=_finish_job, args=(sweep, n)) for n in range(8)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(timeout=60)
        assert job.exitcode == 0
    summary = json.loads((sweep / "jobs.json").read_text())
    assert summary["completed"] == 8 and summary["pending"] == 0


# --- divergence --------------------------------------------------------------------------------

GOOD = {"test/err_mean": 3.0, "test/identity_err_mean": 90.9}


@pytest.mark.parametrize(
    ("metrics", "losses", "diverged"),
    [
        (GOOD, [1.0, 0.1, 0.05], False),
        ({"test/err_mean": 133.6, "test/identity_err_mean": 90.9}, [1.0, 0.9], True),
        ({"test/err_mean": math.nan, "test/identity_err_mean": 90.9}, [], True),
        (GOOD, [1.0, 0.01, 1.5], True),  # 150x its lowest epoch
        (GOOD, [1.0, 0.01, 0.9], False),  # 90x: not orders of magnitude
        (GOOD, [-5.0, -8.0, 900.0], True),  # a negative NLL that blew up
        (GOOD, [-5.0, -8.0, -7.0], False),
        (GOOD, [1.0, math.inf], True),
        ({"test/recon_mean": 0.1}, [0.5, 0.4], False),  # the auto-encoder: no rotation error
    ],
)
def test_divergence_flags_worse_than_identity_or_a_loss_that_grew(metrics, losses, diverged):
    reasons = divergence(metrics, losses)
    assert bool(reasons) is diverged, reasons


@pytest.mark.parametrize(
    ("err", "identity", "untrained"),
    [(90.1, 90.9, True), (85.0, 90.9, True), (80.0, 90.9, False), (1.0, 90.9, False)],
)
def test_a_run_that_barely_beats_the_identity_is_named(err, identity, untrained):
    """The loss=bingham optim.lr=1e-1 case: the NLL fell while the belief widened; the error
    stayed at the identity's (90.1 vs 90.9 deg): not diverged, but said."""
    message = barely_learned({"test/err_mean": err, "test/identity_err_mean": identity})
    assert (message is not None) is untrained
    assert barely_learned({"test/err_mean": err}) is None


# --- SLURM requeue ------------------------------------------------------------------------------


def test_a_requeued_slurm_job_continues_its_own_run(make_cfg, monkeypatch):
    from rotlearn.cli.train import train

    overrides = ["data=tiny", "trainer=cpu", "trainer.enable_progress_bar=false", "logger=none",
                 "net.point_channels=[16,32,64]", "net.head_channels=[32,16]"]  # fmt: skip
    cfg = make_cfg([*overrides, "trainer.max_epochs=1"])
    train(cfg)
    run = Path(cfg.paths.output_dir)
    (run / "metrics.json").unlink()  # as if SLURM had stopped it after its last.ckpt
    again = make_cfg([*overrides, "trainer.max_epochs=2"], run_dir=run)
    with pytest.raises(FileExistsError, match="already holds a run"):
        train(again)  # not on SLURM: a run directory is never reused
    for name, value in {"SLURM_RESTART_COUNT": "1", "SLURM_NTASKS": "1",
                        "SLURM_JOB_NAME": "rotlearn", "SLURM_JOB_ID": "7"}.items():  # fmt: skip
        monkeypatch.setenv(name, value)
    assert train(again)["epochs"] == 2  # the requeued job picks up from last.ckpt


def test_a_requeued_slurm_job_may_start_again_in_its_own_directory(tmp_path, monkeypatch):
    """The command line refuses a taken run directory, but for a requeued SLURM job (asked only
    once the directory is found taken: the SLURM check loads Lightning)."""
    from rotlearn.cli.train import _refuse_an_invalid_new_run

    run = tmp_path / "run"
    run.mkdir()
    (run / "train.log").write_text("epoch 0\n")
    args = ["data=tiny", "trainer.max_epochs=2", f"hydra.run.dir={run}"]
    with pytest.raises(SystemExit, match="already exists and is not empty"):
        _refuse_an_invalid_new_run(args)
    for name, value in {"SLURM_RESTART_COUNT": "1", "SLURM_NTASKS": "1",
                        "SLURM_JOB_NAME": "rotlearn", "SLURM_JOB_ID": "7"}.items():  # fmt: skip
        monkeypatch.setenv(name, value)
    assert _refuse_an_invalid_new_run(args) == args
