"""rotlearn.locks: one process trains a run at a time; the refused one names the holder."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rotlearn.locks import LOCK_FILE, RunLockedError, check_free, hold_run, release_run

HOLD = "import sys, rotlearn.locks as L; L.hold_run(sys.argv[1], 'rotlearn-train ckpt_path=x'); "


def _holder(run, then: str) -> subprocess.Popen:
    """Another process that takes the run's lock, prints 'held', then runs `then`."""
    code = HOLD + "print('held', flush=True); " + then
    job = subprocess.Popen([sys.executable, "-c", code, str(run)], stdout=subprocess.PIPE,
                           stdin=subprocess.PIPE, text=True)  # fmt: skip
    assert job.stdout.readline().strip() == "held"
    return job


def test_a_held_run_is_refused_naming_the_holder(tmp_path):
    job = _holder(tmp_path, "sys.stdin.read()")
    try:
        for attempt in (check_free, hold_run):
            with pytest.raises(RunLockedError) as info:
                attempt(tmp_path)
            message = str(info.value)
            assert f"{tmp_path} is in use by pid {job.pid} on " in message
            assert "(rotlearn-train ckpt_path=x)" in message
    finally:
        job.communicate("")
    hold_run(tmp_path)  # released when its holder ended
    release_run(tmp_path)


def test_a_stale_lock_is_taken_over_and_said(tmp_path, caplog):
    job = _holder(tmp_path, "import os; os._exit(0)")  # dies without releasing
    job.wait()
    assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == job.pid
    with caplog.at_level("WARNING", logger="rotlearn"):
        hold_run(tmp_path)
    assert f"took over the stale lock of pid {job.pid}" in caplog.text
    release_run(tmp_path)
    assert (tmp_path / LOCK_FILE).read_text() == ""  # a clean release leaves no holder


def test_checking_a_run_creates_nothing(tmp_path):
    check_free(tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_the_lock_is_reentrant_within_a_process(tmp_path):
    hold_run(tmp_path)
    hold_run(tmp_path)
    check_free(tmp_path)
    release_run(tmp_path)


def test_a_symlinked_lock_file_is_never_written_through(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / LOCK_FILE).symlink_to(victim)
    with pytest.raises(ValueError, match="lock file"):
        hold_run(run)
    assert victim.read_text() == "precious\n"


@pytest.mark.parametrize(
    "holder",
    [
        {"pid": 1, "started": "yesterday"},
        {"pid": 1, "started": 1e300},
        {"pid": "1\x1b[2J\x07", "host": "h" * 3000, "started": None, "command": ["x"]},
    ],
)
def test_a_stale_lock_file_a_run_came_with_is_shown_as_plain_text(tmp_path, caplog, holder):
    """A received run may carry its .rotlearn.lock: a start time that is no time raised a
    TypeError or OverflowError traceback; a field with terminal escapes or of any length was
    printed as it was. The holder is said in one plain, bounded line."""
    (tmp_path / LOCK_FILE).write_text(json.dumps(holder))
    with caplog.at_level("WARNING", logger="rotlearn"):
        hold_run(tmp_path)
    release_run(tmp_path)
    said = caplog.records[-1].getMessage()
    assert "took over the stale lock of pid 1" in said and "since ?" in said
    assert all(c.isprintable() for c in said) and len(said) < 1000
