"""rotlearn-report's beliefs section from fabricated run directories: the table per setting (NLL,
ECE, the untempered belief, every score's Spearman and AUROC) and the reliability diagram."""

from __future__ import annotations

import json
from pathlib import Path

import yaml
from PIL import Image

from rotlearn.bingham import CREDIBLE_LEVELS
from rotlearn.report import make_report


def _run(run: Path, rep: str, loss: str, metrics: dict) -> None:
    """A completed run directory with the given metrics.json."""
    (run / ".hydra").mkdir(parents=True)
    config = {"rep": {"name": rep}, "loss": {"_target_": f"rotlearn.losses.{loss}"}, "seed": 0}
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    choices = {"rep": rep, "loss": loss}
    (run / ".hydra" / "hydra.yaml").write_text(
        yaml.safe_dump({"hydra": {"runtime": {"choices": choices}}})
    )
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"rep={rep}", f"loss={loss}"]))
    base = {"test/err_mean": 3.0, "test/err_median": 2.0, "test/raw_norm_spearman": -0.1}
    (run / "metrics.json").write_text(json.dumps({**base, **metrics}))
    (run / "status.json").write_text(json.dumps({"status": "COMPLETED"}))


def _belief(ece: float, prefix: str = "test/", shift: float = 0.0) -> dict:
    cover = {f"{prefix}coverage_{a:g}": min(1.0, a + shift) for a in CREDIBLE_LEVELS}
    return {f"{prefix}nll": -5.0 + shift, f"{prefix}ece": ece, **cover}


def test_runs_with_beliefs_get_a_table_and_a_reliability_diagram(tmp_path):
    sweep = tmp_path / "beliefs"
    tempered = {**_belief(0.01), **_belief(0.2, "test/uncalibrated_", 0.2),
                "test/temperature": 2.5, "test/dt_spearman": 0.7, "test/dt_auroc_noisiest": 0.9,
                "test/eigengap_spearman": -0.6}  # fmt: skip
    _run(sweep / "0", "a", "chordal", tempered)
    _run(sweep / "1", "a", "bingham", {**_belief(0.02), "test/dt_spearman": 0.5})
    _run(sweep / "2", "a", "bingham", {**_belief(0.04), "test/dt_spearman": 0.6})
    _run(sweep / "3", "sixd", "chordal", {"test/raw_norm_auroc_noisiest": 0.6})
    files = make_report(sweep)
    md = (sweep / "report.md").read_text()
    assert "## Beliefs" in md
    header = next(line for line in md.splitlines() if line.startswith("| setting | runs | median"))
    for column in ("NLL (nats)", "ECE", "T", "NLL at T = 1", "ECE at T = 1", "dt Spearman",
                   "eigengap Spearman", "raw_norm Spearman", "dt AUROC noisiest",
                   "raw_norm AUROC noisiest"):  # fmt: skip
        assert f"| {column} |" in header, column
    rows = {line.split(" | ")[0][2:]: line for line in md.splitlines() if line.startswith("| a ")}
    assert set(rows) == {"a loss=chordal", "a loss=bingham"}
    # two bingham runs: medians of ECE 0.02 and 0.04, of Spearman 0.5 and 0.6
    assert "| a loss=bingham | 2 | 2.000 | -5.000 | 0.030 | - | - | - | 0.550 | - | -0.100 |" in md
    assert "| a loss=chordal | 1 | 2.000 | -5.000 | 0.010 | 2.5 | -4.800 | 0.200 | 0.700 |" in md
    assert header.endswith("| dt AUROC noisiest | raw_norm AUROC noisiest |")
    assert any(line.startswith("| sixd loss=chordal | 1 | 2.000 | - |") for line in md.splitlines())
    assert files["reliability"] == sweep / "reliability.png"
    assert Image.open(files["reliability"]).size[0] > 300
    assert "![reliability diagram](reliability.png)" in md
    assert "AUROC noisiest: how well the score flags the noisiest tenth" in md
    # without a noise level no run has the AUROC noisiest columns: the text names none
    other = tmp_path / "no_noise"
    _run(other / "0", "a", "bingham", {**_belief(0.02), "test/dt_spearman": 0.5})
    make_report(other)
    assert "noisiest" not in (other / "report.md").read_text()


def test_runs_without_belief_metrics_get_no_beliefs_section(tmp_path):
    sweep = tmp_path / "plain"
    _run(sweep / "0", "quat", "chordal", {})
    (sweep / "0" / "metrics.json").write_text(json.dumps({"test/err_mean": 3.0,
                                                          "test/err_median": 2.0}))  # fmt: skip
    files = make_report(sweep)
    assert "reliability" not in files
    assert "Beliefs" not in (sweep / "report.md").read_text()


def test_a_remedy_names_its_setting_escaped_and_reads_plainly(tmp_path):
    """The remedy's line escapes the setting (received text), not rotlearn's own words: the raw
    report.md read 'ECE 0.30 &gt; 0.1' once every remedy was escaped whole."""
    sweep = tmp_path / "remedy"
    _run(sweep / "0", "a", "chordal", _belief(0.3))
    _run(sweep / "1", "sixd", "chordal", {"test/raw_norm_auroc_noisiest": 0.6})
    make_report(sweep)
    md = (sweep / "report.md").read_text()
    assert "- a: uncalibrated (ECE 0.30 > 0.1); try calibrate=true" in md, md
