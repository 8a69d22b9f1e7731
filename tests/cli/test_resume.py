"""Resume after SIGKILL: the same run directory, the same final numbers as an uninterrupted run."""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from rotlearn.cli.resume import keep_earlier_records, resume_arguments
from tests.conftest import (
    RESUMABLE,
    SMALL_NET,
    checkpoint_epoch,
    copy_run,
    model_checkpoint,
    run_cli,
    start_cli,
    within,
)


def test_sigkill_then_resume_matches_an_uninterrupted_run(tmp_path):
    run = tmp_path / "run"
    job = start_cli([*RESUMABLE, f"hydra.run.dir={run}"], tmp_path)
    last = run / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 300
    while checkpoint_epoch(last) < 1:  # killed after its 2nd checkpoint (epoch index 1)
        assert job.poll() is None, f"training ended before it could be killed: {job.stderr.read()}"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    job.send_signal(signal.SIGKILL)
    job.wait()
    killed_at = checkpoint_epoch(last)
    assert not (run / "metrics.json").exists() and killed_at < 5, "the run finished before the kill"

    resumed = run_cli([f"ckpt_path={run}"], tmp_path, warnings=True)  # Python's own filters
    assert resumed.returncode == 0, resumed.stderr
    # a resume continues in its own checkpoints/: Lightning's alarm about it is not shown
    said = resumed.stdout + resumed.stderr  # Hydra logs warnings to stdout and train.log
    assert "exists and is not empty" not in said, said
    reference = start_cli([*RESUMABLE, f"hydra.run.dir={tmp_path / 'reference'}"], tmp_path)
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
    model_checkpoint(run / "checkpoints" / "last.ckpt", overrides)
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
        f"ckpt_path='{(new / 'checkpoints' / 'last.ckpt').resolve()}'",  # quoted for Hydra
        f"hydra.run.dir='{new.resolve()}'",
        "hydra.mode=RUN",
    ]
    assert resume_arguments([f"ckpt_path={old}"])[0] == "rep=sixd"
    assert resume_arguments(["rep=a"]) == ["rep=a"]
    assert resume_arguments(["ckpt_path=null"]) == ["ckpt_path=null"]


def test_a_run_of_an_experiment_that_sweeps_resumes_as_that_run(tmp_path):
    """experiment=beliefs sets hydra.mode=MULTIRUN; a run of it with hydra.mode=RUN (which
    Hydra does not save among the overrides) was resumed as a new one-job sweep under
    outputs/multirun, its own records moved to history/1 and never written again."""
    tiny = ["data.num_val=16", "data.num_test=16", "data.batches_per_epoch=1",
            "data.eval_batch_size=16", "data.batch_size=8", "trainer.enable_progress_bar=false",
            "logger=csv", *SMALL_NET]  # fmt: skip
    run = tmp_path / "outputs" / "runs" / "r"
    args = ["experiment=beliefs", "variant=a_bingham", "trainer.max_epochs=1", *tiny]
    done = run_cli([*args, "hydra.mode=RUN", f"hydra.run.dir={run}"], tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    done = run_cli([f"ckpt_path={run}", "trainer.max_epochs=2"], tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((run / "metrics.json").read_text())["epochs"] == 2
    assert sorted(p.name for p in (tmp_path / "outputs").iterdir()) == ["runs"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["-m", "ckpt_path=last"], "cannot be used with -m"),
        (
            ["ckpt_path=last"],
            r"no run under .*A run made elsewhere \(hydra\.run\.dir=\.\.\.\) "
            r"resumes by its folder: ckpt_path=<run dir>",
        ),
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


# --- issue 13: a refused resume changes nothing; a completed run only trains longer -----------


def _hashes(run: Path) -> dict[str, str]:
    """sha256 of every file below `run`, by relative path."""
    return {
        str(p.relative_to(run)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(run.rglob("*"))
        if p.is_file()
    }


def _completed_run(finished_run: Path, cwd: Path, name: str) -> Path:
    """A finished one-epoch run made by the CLI (the session's, copied) in
    `<cwd>/outputs/runs/<name>`."""
    run = copy_run(finished_run, cwd / "outputs" / "runs" / name)
    assert json.loads((run / "status.json").read_text())["status"] == "COMPLETED"
    return run


@pytest.fixture(scope="module")
def completed(tmp_path_factory, finished_run) -> Path:
    cwd = tmp_path_factory.mktemp("completed")
    _completed_run(finished_run, cwd, "2026-01-02_00-00-00-000000")
    return cwd


def test_a_refused_resume_from_the_command_line_leaves_the_run_byte_identical(completed):
    run = completed / "outputs" / "runs" / "2026-01-02_00-00-00-000000"
    before = _hashes(run)
    job = start_cli([f"ckpt_path={run}", "optim.lr=0.5", "seed=99"], completed)
    assert job.wait(timeout=300) != 0
    message = job.stderr.read()
    assert f"refusing to resume {run}" in message and "COMPLETED" in message
    assert "optim.lr=0.5 seed=99" in message
    assert _hashes(run) == before


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["ckpt_path=RUN", "optim.lr=0.5", "seed=99"], "also sets optim.lr=0.5 seed=99"),
        (["ckpt_path=RUN"], "trainer.max_epochs=<more>, above 1"),
        (["ckpt_path=RUN", "trainer.max_epochs=1"], "trainer.max_epochs=1 is not above 1"),
        (["ckpt_path=last"], "no run under .* can be resumed .*1 have one but are COMPLETED"),
        (["ckpt_path=last", "trainer.max_epochs=5"], "no run under .* can be resumed"),
    ],
)
def test_resuming_a_completed_run_is_refused_before_anything_is_written(
    completed, monkeypatch, argv, message
):
    monkeypatch.chdir(completed)
    runs = completed / "outputs" / "runs"
    run = runs / "2026-01-02_00-00-00-000000"
    before = _hashes(run)
    argv = [a.replace("RUN", str(run)) for a in argv]
    with pytest.raises(SystemExit, match=message):
        resume_arguments(argv, runs_root=runs)
    assert _hashes(run) == before


def test_ckpt_path_last_skips_completed_runs_and_names_its_pick(tmp_path, capsys):
    older = _fake_run(tmp_path, "2026-01-01_00-00-00-000000", ["rep=sixd"])
    (older / "status.json").write_text(json.dumps({"status": "INTERRUPTED"}))
    newer = _fake_run(tmp_path, "2026-01-02_00-00-00-000000", ["rep=quat"])
    (newer / "metrics.json").write_text(json.dumps({"epochs": 3}))
    args = resume_arguments(["ckpt_path=last"], runs_root=tmp_path)
    assert f"hydra.run.dir='{older.resolve()}'" in args and args[0] == "rep=sixd"
    said = capsys.readouterr().err
    assert f"resuming {older}" in said and "skipped 1 newer COMPLETED" in said


def test_a_completed_run_trains_longer_and_keeps_its_earlier_records(tmp_path, finished_run):
    run = _completed_run(finished_run, tmp_path, "2026-01-03_00-00-00-000000")
    records = ["metrics.json", "status.json", "timing.json", "test_errors.json", "csv/metrics.csv",
               ".hydra/config.yaml", ".hydra/overrides.yaml", ".hydra/hydra.yaml"]  # fmt: skip
    before = {name: (run / name).read_bytes() for name in records}
    job = start_cli([f"ckpt_path={run}", "trainer.max_epochs=2"], tmp_path)
    assert job.wait(timeout=300) == 0, job.stderr.read()
    for name, content in before.items():  # the first attempt's records, unchanged
        assert (run / "history" / "1" / name).read_bytes() == content, name
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["epochs"] == 2 and json.loads(before["metrics.json"])["epochs"] == 1
    assert json.loads((run / "status.json").read_text())["status"] == "COMPLETED"
    assert "trainer.max_epochs=2" in (run / ".hydra" / "overrides.yaml").read_text()
    # logger=csv: Lightning deleted the first attempt's log (its epoch was lost); the report's
    # curve reads both
    from rotlearn.report.document import _curve

    first = pd.read_csv(run / "history" / "1" / "csv" / "metrics.csv")
    second = pd.read_csv(run / "csv" / "metrics.csv")
    assert set(first["epoch"].dropna()) == {0} and set(second["epoch"].dropna()) == {1}
    curve = _curve(run, "val/err_mean")
    assert list(curve) == [*first["val/err_mean"].dropna(), *second["val/err_mean"].dropna()]


def test_keep_earlier_records_numbers_each_attempt(tmp_path):
    run = _fake_run(tmp_path, "run", ["rep=a"])
    for attempt in (1, 2):
        (run / "status.json").write_text(json.dumps({"attempt": attempt}))
        assert keep_earlier_records(run) == run / "history" / str(attempt)
        assert not (run / "status.json").exists()
        assert (run / ".hydra" / "overrides.yaml").is_file()  # Hydra rewrites it; kept till then
    assert json.loads((run / "history" / "2" / "status.json").read_text()) == {"attempt": 2}
    assert (run / "history" / "1" / ".hydra" / "overrides.yaml").read_text() == "- rep=a\n"


def test_keep_earlier_records_refuses_a_received_history_it_cannot_keep_and_changes_nothing(
    tmp_path,
):
    """A received run crashed the resume with a traceback once its lock was taken: a folder
    history/² (a digit to str.isdigit, not to int), a history that is a file, a config over its
    cap (which also left history/.1.*.partial behind). One is skipped, the others refused."""
    from rotlearn.io import MAX_BYTES, UnreadableFileError

    def tree(run: Path) -> dict[str, str]:
        return {**_hashes(run), **{str(p.relative_to(run)): "dir" for p in run.rglob("*")
                                   if p.is_dir()}}  # fmt: skip

    run = _fake_run(tmp_path, "numbered", ["rep=a"])
    (run / "status.json").write_text("{}")
    (run / "history" / "²").mkdir(parents=True)
    assert keep_earlier_records(run) == run / "history" / "1"
    file_history = _fake_run(tmp_path, "file", ["rep=a"])
    (file_history / "history").write_text("x")
    large_config = _fake_run(tmp_path, "large", ["rep=a"])
    big = b"#" * (MAX_BYTES["YAML config"] + 1)
    (large_config / ".hydra" / "hydra.yaml").write_bytes(big)
    for run, name in ((file_history, "history"), (large_config, ".hydra/hydra.yaml")):
        (run / "status.json").write_text("{}")
        before = tree(run)
        with pytest.raises(UnreadableFileError, match=re.escape(str(run / name))):
            keep_earlier_records(run)
        assert tree(run) == before  # no partial folder, every record in place


def test_the_earlier_tests_tensorboard_session_is_kept_out_of_tensorboards_view(tmp_path):
    """TensorBoard shows a run's first HPARAMS session: a finished run trained longer showed the
    first attempt's settings (trainer.max_epochs=2) beside the new results. The earlier test's
    event files move to the history, renamed so TensorBoard does not read them; the training
    and validation curves go on in the run."""
    run = _fake_run(tmp_path, "run", ["rep=a"])
    (run / "metrics.json").write_text("{}")
    board = run / "tensorboard" / "rep=a"
    for sub, content in (("train", b"curve"), ("val", b"curve"), ("test", b"session")):
        (board / sub).mkdir(parents=True)
        (board / sub / "events.out.tfevents.1.host.7.0").write_bytes(content)
    kept = keep_earlier_records(run)
    assert not list((board / "test").iterdir())
    assert (board / "train" / "events.out.tfevents.1.host.7.0").read_bytes() == b"curve"
    moved = kept / "tensorboard" / "rep=a" / "test" / "events.out.kept.1.host.7.0"
    assert moved.read_bytes() == b"session"
    assert not [p for p in kept.rglob("*") if "tfevents" in p.name]


def test_a_resume_names_a_misspelt_key_and_takes_an_argument_its_yaml_leaves_out(tmp_path):
    """The user's new keys on a resume get what a new run's get (issue 23): a misspelt one is
    refused with rotlearn's "did you mean", not Hydra's append advice about the run's file; a
    constructor argument the YAML does not list is passed with `+`."""
    run = _fake_run(tmp_path, "run", ["rep=quat"])
    (run / "status.json").write_text(json.dumps({"status": "INTERRUPTED"}))
    with pytest.raises(SystemExit) as refused:
        resume_arguments([f"ckpt_path={run}", "optim.lrr=1e-3"])
    said = str(refused.value)
    assert "optim.lrr: unknown key; did you mean optim.lr?" in said
    assert "overrides.yaml" not in said and "+optim.lrr" not in said
    args = resume_arguments([f"ckpt_path={run}", "optim.amsgrad=true"])
    assert args[:2] == ["rep=quat", "+optim.amsgrad=true"]


def test_a_run_file_of_many_unknown_keys_is_refused_in_one_composition(tmp_path):
    """Only the user's own new keys get a `+` on a resume: 300 unknown keys in a received
    run's overrides.yaml are refused at once, naming the file (one `+` and one composition
    each took 12 s for 100 keys, growing with the square)."""
    run = _fake_run(tmp_path, "run", ["rep=quat"])
    bogus = "".join(f"- optim.bogus{i}=1\n" for i in range(300))
    (run / ".hydra" / "overrides.yaml").write_text(bogus)
    (run / "status.json").write_text(json.dumps({"status": "INTERRUPTED"}))
    refused = r"config key optim\.bogus0: unknown key; .*overrides\.yaml: 'optim\.bogus0=1'\)$"
    with within(20), pytest.raises(SystemExit, match=refused):
        resume_arguments([f"ckpt_path={run}", "optim.amsgrad=true"])


def test_a_damaged_overrides_file_does_not_resume_the_run_under_other_settings(
    tmp_path, finished_run, monkeypatch
):
    """A run whose .hydra/overrides.yaml lost a line (here data=tiny) composes another config
    than the one it trained: the resume is refused, naming the key and both files, and the run
    is left byte-identical (before, it resumed the checkpoint on the default data)."""
    run = copy_run(finished_run, tmp_path / "outputs" / "runs" / "cut", resumable=True)
    overrides = run / ".hydra" / "overrides.yaml"
    kept = [o for o in yaml.safe_load(overrides.read_text()) if o != "data=tiny"]
    overrides.write_text(yaml.safe_dump(kept))
    before = _hashes(run)
    monkeypatch.chdir(tmp_path)
    refused = (
        r"refusing to resume .*config key data\.batch_size: .*overrides\.yaml composes 100,"
        r" but the run trained with 8 \(.*config\.yaml\): the overrides file is damaged"
    )
    with pytest.raises(SystemExit, match=refused):
        resume_arguments([f"ckpt_path={run}", "trainer.max_epochs=2"], run.parent)
    assert _hashes(run) == before
    # the command line may change what it names: the run's own overrides then resume it
    overrides.write_text(yaml.safe_dump([*kept, "data=tiny"]))
    args = resume_arguments(
        [f"ckpt_path={run}", "trainer.max_epochs=2"], tmp_path / "outputs" / "runs"
    )
    assert "trainer.max_epochs=2" in args


@pytest.mark.parametrize(
    ("saved", "message"),
    [
        (["rep=nosuch"], r"config key rep: no option 'nosuch'; options: a, fisher, quat, sixd, "
         r"svd9d \(from .*run/\.hydra/overrides\.yaml: 'rep=nosuch'\)$"),
        (["rep=quat", "data.batch_size=0"], r"config key data\.batch_size: should be greater "
         r"than 0, got 0 \(from .*overrides\.yaml: 'data\.batch_size=0'\)$"),
        (["rep=quat", "nosuch.key=1"], r"config key nosuch: unknown key; allowed: calibrate, .*"
         r"trainer \(from .*overrides\.yaml: 'nosuch\.key=1'\)$"),  # no append advice
        (["rep=quat", "data.sigma=${oc.env:HOME}"], r"overrides\.yaml: override 'data\.sigma="
         r"\$\{oc\.env:HOME\}' reads \$\{oc\.env:\.\.\.\}: a saved override may use only the "
         r"resolvers that read the config"),
        # a resolver whose name is built from another, and one that reads a string as config
        (["rep=quat", "data.sigma='${oc.${oc.decode:env}:HOME}'"], r"overrides\.yaml: override "
         r".data\.sigma=.*. reads \$\{oc\.\$\{oc\.decode:env\}:\.\.\.\}: a saved override"),
        (["rep=quat", r"""data.sigma="${oc.decode:'\${oc.env:HOME}'}" """], r"overrides\.yaml: "
         r"override .data\.sigma=.*. reads \$\{oc\.decode:\.\.\.\}: a saved override"),
        (["rep=quat", "optim.lr=1e-3}"], r"overrides\.yaml: override 'optim\.lr=1e-3\}' is not "
         r"Hydra's override grammar \(extraneous input '\}'\)$"),  # was Hydra's 3 lines
        (["rep=quat", "data.sigma='${oc.env:HOME'"], r"overrides\.yaml: override .data\.sigma="
         r".*. holds '\$\{oc\.env:HOME', which OmegaConf cannot read$"),
    ],
)  # fmt: skip
def test_a_refusal_names_the_saved_override_the_user_did_not_type(tmp_path, saved, message):
    """A resume replays the run's saved overrides: a refusal for one of them names the file and
    the override (the user never typed it), in one line; an environment variable a received
    run's file names is never read into its config (it was, and printed: 'got /root')."""
    run = _fake_run(tmp_path, "run", ["rep=quat"])
    (run / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in saved))
    (run / "status.json").write_text(json.dumps({"status": "INTERRUPTED"}))
    with pytest.raises(SystemExit) as refused:
        resume_arguments([f"ckpt_path={run}", "trainer.max_epochs=3"])
    said = str(refused.value)
    assert re.search(message, said) and "\n" not in said and os.environ["HOME"] not in said
