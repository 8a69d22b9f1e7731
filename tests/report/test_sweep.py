"""A real 2 x 2 sweep (rep x optim.lr, tiny data) read as a person reads it: four settings in
summary.csv, report.md and the curves' legend, never pooled; each job in its own directory, its
TensorBoard run named by what the sweep varies; one model summary; every file readable by all
(umask 022)."""

from __future__ import annotations

import json

import pandas as pd
from omegaconf import OmegaConf

from rotlearn.report import document, figures
from tests.conftest import FAST, modes, run_cli

SETTINGS = ["a optim.lr=0.0001", "a optim.lr=0.001", "sixd optim.lr=0.0001", "sixd optim.lr=0.001"]


def test_a_two_by_two_sweep_gives_four_settings_everywhere(tmp_path, monkeypatch):
    sweep = tmp_path / "sweep"
    fast = [a for a in FAST if not a.startswith("trainer.enable_progress_bar")]
    args = ["-m", "rep=a,sixd", "optim.lr=1e-4,1e-3", "trainer.max_epochs=2", *fast,
            f"hydra.sweep.dir={sweep}"]  # fmt: skip
    result = run_cli(args, tmp_path, umask=0o022)
    assert result.returncode == 0, result.stderr[-3000:]
    printed = result.stdout + result.stderr
    assert printed.count("Trainable params") == 1  # the model summary once per sweep
    # each job: its own directory, metrics and config
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit())
    seen = set()
    for job in jobs:
        metrics = json.loads((job / "metrics.json").read_text())
        saved = OmegaConf.load(job / ".hydra" / "config.yaml")
        assert saved.rep.name == metrics["rep"] and (job / "checkpoints" / "last.ckpt").is_file()
        seen.add((metrics["rep"], saved.optim.lr))
        # TensorBoard: named by what the sweep varies, the job's directory keeps its place
        (name,) = [p.name for p in (job / "tensorboard").iterdir()]
        assert name == f"rep={metrics['rep']},optim.lr={saved.optim.lr:g}"
    assert len(seen) == 4
    # summary.csv and report.md: four settings of one run each
    summary = pd.read_csv(sweep / "summary.csv")
    assert sorted(summary["setting"]) == SETTINGS
    report = (sweep / "report.md").read_text()
    for setting in SETTINGS:
        assert f"| {setting} | 1 |" in report
    assert "4 setting(s) of completed runs" in report
    # the curves plot: one legend entry per setting (the same drawing, captured)
    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path, dpi=100: drawn.append(fig))
    files = document.make_report(sweep, out=tmp_path / "again")
    (curves,) = [fig for fig in drawn if fig.legends and "error" in fig.axes[0].get_title()]
    assert sorted(t.get_text() for t in curves.legends[0].get_texts()) == SETTINGS
    assert (sweep / "curves.png").stat().st_size > 10_000 and "summary" in files
    # umask 022: every file of the sweep readable by all, every folder enterable
    written = modes(sweep)
    wrong = {
        p: oct(m) for p, m in written.items() if m != (0o755 if (sweep / p).is_dir() else 0o644)
    }
    assert not wrong, wrong
