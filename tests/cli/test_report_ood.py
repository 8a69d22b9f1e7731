"""rotlearn-report's OOD sections from fabricated run directories: Table I beside the paper's, the
per-score table, the error per test set (Fig. 8), the OOD figures, and pooling several sweeps."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import torch
import yaml

from rotlearn.cli.report import main as report_main
from rotlearn.ood import mixed_set, rejection_table
from rotlearn.ood.records import write_samples
from rotlearn.report import make_report
from rotlearn.report.tables import mean_range
from rotlearn.scores import SCORES

PAPER = {
    "source": "paper Table I, sequence 00",
    "where": {"loss": "chordal"},
    "rows": [
        {"rep": "quat", "clean_err": 0.16, "clean_kept": 100, "corrupted_err": 0.74,
         "corrupted_kept": 100},
        {"rep": "a", "score": "dt", "clean_err": 0.12, "clean_kept": 69.5, "corrupted_err": 0.12,
         "corrupted_kept": 37.3, "precision": 99.0},
    ],
}  # fmt: skip


def _sets(separation: float, extra: bool) -> dict[str, dict[str, torch.Tensor]]:
    """Scores of 40 train, 20 test pairs (the last 10 erased): erased pairs score `separation`
    higher (less confident for DT), with 4x the error."""
    g = torch.Generator().manual_seed(0)
    train = torch.randn(40, generator=g, dtype=torch.float64)
    clean = torch.randn(20, generator=g, dtype=torch.float64)
    ood = torch.arange(20) >= 10
    err = torch.rand(20, generator=g, dtype=torch.float64) + 1
    sets = {
        "val": {"error": torch.ones(40, dtype=torch.float64), "dt": train},
        "clean": {"error": err, "dt": clean, "corrupted": torch.zeros(20, dtype=torch.bool)},
        "corrupted": {"error": torch.where(ood, 4 * err, err), "dt": clean + separation * ood,
                      "corrupted": ood},
        "noise": {"error": torch.full((4,), 90.0, dtype=torch.float64),
                  "dt": torch.full((4,), 9.0, dtype=torch.float64)},
    }  # fmt: skip
    if extra:
        indoor = {"error": 3 * err[:5], "dt": clean[:5] + separation}
        sets["indoor"] = mixed_set(sets["clean"], indoor)
    return sets


def _fabricate_run(run: Path, rep: str, loss: str, report: dict, extra: bool = False,
                   seed: int = 0, separation: float | None = None) -> None:  # fmt: skip
    """A completed run directory as `rotlearn-train` with `callbacks=ood` leaves it."""
    (run / ".hydra").mkdir(parents=True)
    config = {"rep": {"name": rep}, "loss": {"_target_": f"rotlearn.losses.{loss}"},
              "seed": seed, "report": report}  # fmt: skip
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    choices = {"rep": rep, "loss": loss, "hydra/launcher": "basic"}
    (run / ".hydra" / "hydra.yaml").write_text(
        yaml.safe_dump({"hydra": {"runtime": {"choices": choices}}})
    )
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"rep={rep}", f"seed={seed}"]))
    if separation is None:
        separation = 3.0 if rep == "a" else -3.0
    sets = _sets(separation, extra)
    scores = [SCORES["dt"]] if rep == "a" else [SCORES["raw_norm"]]
    if rep != "a":  # fabricate the raw norm as minus the DT values (keep-above)
        for data in sets.values():
            data["raw_norm"] = -data.pop("dt")
    frame = rejection_table(sets, scores, [0.5, 0.75, 1.0], {"dt": 0.75, "raw_norm": 0.75})
    frame.insert(0, "rep", rep)
    frame.to_csv(run / "ood.csv", index=False)
    write_samples(run, sets)
    metrics = {"test/err_mean": float(sets["clean"]["error"].mean()), "test/err_median": 1.5}
    (run / "metrics.json").write_text(json.dumps(metrics))
    (run / "status.json").write_text(json.dumps({"status": "COMPLETED"}))


def test_table_one_is_shown_beside_the_paper_and_pooled_runs_are_named(tmp_path):
    report = {"paper": PAPER, "ood": {"quantiles": [0.75]}}
    sweep, single = tmp_path / "kitti", tmp_path / "kitti_bingham"
    _fabricate_run(sweep / "0", "quat", "chordal", report)
    _fabricate_run(sweep / "1", "a", "chordal", report)
    _fabricate_run(single, "a", "bingham", report)
    (sweep / "1" / "ood_examples.png").write_bytes(b"\x89PNG fake")
    files = make_report([sweep, single])
    assert files["report"] == sweep / "report.md"
    assert {"ood_pr", "ood_scatter", "ood_box"} <= set(files)
    assert all(files[k].stat().st_size > 1000 for k in ("ood_pr", "ood_scatter", "ood_box"))
    text = files["report"].read_text()
    table = pd.read_csv(files["ood_table"])
    assert set(table["job"]) == {"kitti/0", "kitti/1", "kitti_bingham"}
    assert set(table["method"]) >= {"a loss=chordal + DT", "a loss=bingham + DT"}
    lines = text.splitlines()
    side = lines.index("### Side by side with the paper (paper Table I, sequence 00)")
    dt_row = next(line for line in lines[side:] if line.startswith("| a loss=chordal + DT |"))
    ours = table[table["method"] == "a loss=chordal + DT"].iloc[0]
    assert f"{ours['precision %']:.2f} (99)" in dt_row and "(37.3)" in dt_row
    assert "| quat loss=chordal | 1 | quat | " in text
    bingham = next(line for line in lines[side:] if line.startswith("| a loss=bingham + DT |"))
    assert "| - |" in bingham and "(-)" in bingham  # no paper row for the trained belief
    # every run with samples gets the oracle row in Table I, none beside the paper
    oracle = table[table["score"] == "error"]
    assert set(oracle["method"]) == {"a loss=chordal + own error (oracle)",
                                     "a loss=bingham + own error (oracle)",
                                     "quat loss=chordal + own error (oracle)"}  # fmt: skip
    paper_section = lines[side : lines.index("## OOD scores on each test set")]
    assert not any("oracle" in line for line in paper_section)
    # the per-score table: AUROC 1 for the separated A runs, 0 for the reversed quat norm
    scores = lines.index("## OOD scores on each test set")
    erased = [line.split("|") for line in lines[scores:] if "| test, half erased |" in line]
    auroc = {cells[1].strip(): cells[3].strip() for cells in erased}
    assert auroc == {"a loss=chordal + DT": "1.00", "a loss=bingham + DT": "1.00",
                     "quat loss=chordal + norm": "0.00"}  # fmt: skip
    assert all(cells[4].strip() == "0.75" for cells in erased)
    assert "](kitti/1/ood_examples.png)" not in text and "](1/ood_examples.png)" in text
    assert "Error per test set" not in text  # no extra sets
    summary = pd.read_csv(files["summary"])
    assert "group:loss" in summary and "group:hydra/launcher" not in summary


def test_a_crafted_paper_table_in_a_runs_config_is_shown_not_obeyed(tmp_path):
    """The paper's rows come from a run's config (untrusted): a value that is no number, a row
    that is no mapping, a head that is a mapping give '-' cells, not a crash."""
    rows = [{"rep": "a", "score": "dt", "clean_err": "abc", "precision": [1, 2],
             "clean_kept": True}, "junk", {"rep": {"x": 1}}]  # fmt: skip
    report = {"paper": {**PAPER, "rows": rows}, "ood": {"quantiles": [0.75]}}
    _fabricate_run(tmp_path / "a", "a", "chordal", report)
    lines = make_report([tmp_path / "a"])["report"].read_text().splitlines()
    side = lines.index("### Side by side with the paper (paper Table I, sequence 00)")
    dt = next(line for line in lines[side:] if line.startswith("| a + DT |"))
    cells = [c.strip() for c in dt.split("|")[1:-1]]
    assert cells[3].endswith("(-)") and cells[4].endswith("(-)") and cells[7].endswith("(-)")
    assert any(line.startswith("| (not run) |") for line in lines[side:])


def test_runs_differing_only_in_their_seeds_get_mean_and_range(tmp_path):
    """Three seeds of one setting pool into one row of the seeds table: the mean and range of
    each number over the seeds, beside the per-job rows (whose numbers they must match)."""
    report = {"ood": {"quantiles": [0.75]}, "paper": {**PAPER, "where": {"loss": "bingham"}}}
    for seed, separation in enumerate((0.0, 1.0, 3.0)):  # chance, some, perfect separation
        _fabricate_run(tmp_path / "a" / str(seed), "a", "bingham", report, seed=seed,
                       separation=separation)  # fmt: skip
    _fabricate_run(tmp_path / "quat", "quat", "bingham", report)
    files = make_report([tmp_path / "a", tmp_path / "quat"])
    table = pd.read_csv(files["ood_table"])
    dt = table[table["method"] == "a + DT"]
    assert len(dt) == 3 and dt["AUROC"].nunique() == 3
    lines = files["report"].read_text().splitlines()
    start = lines.index("### Over seeds: mean (min-max)")
    row = next(line for line in lines[start:] if line.startswith("| a + DT |"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[1] == "3"  # runs
    auroc = dt["AUROC"].to_numpy()
    assert cells[-1] == f"{auroc.mean():.2f} ({auroc.min():.2f}-{auroc.max():.2f})"
    quat = next(line for line in lines[start:] if line.startswith("| quat |"))
    assert quat.split("|")[2].strip() == "1"  # one run: its numbers alone, no range
    assert "(" not in quat.split("|")[4]
    # beside the paper: one row per method, its seeds pooled the same way
    side = lines.index("### Side by side with the paper (paper Table I, sequence 00)")
    end = next(i for i in range(side + 1, len(lines)) if lines[i].startswith("#"))
    rows = [line for line in lines[side:end] if line.startswith("| a + DT |")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].split("|")[1:-1]]
    assert cells[1:3] == ["3", "a + DT"]
    assert cells[-1] == f"{auroc.mean():.2f} ({auroc.min():.2f}-{auroc.max():.2f})"
    assert cells[4] == f"{mean_range(dt['clean kept %'], '[]')} (69.5)"  # as seeds_table


def test_extra_sets_give_the_error_per_test_set(tmp_path, capsys):
    report = {"ood": {"sets": {"clean": "outdoor", "indoor": "outdoor + indoor"}}}
    sweep = tmp_path / "mav"
    _fabricate_run(sweep / "0", "sixd", "chordal", report, extra=True)
    _fabricate_run(sweep / "1", "a", "chordal", report, extra=True)
    assert report_main([str(sweep), "--out", str(tmp_path / "out")]) == 0
    text = (tmp_path / "out" / "report.md").read_text()
    lines = text.splitlines()
    start = lines.index("## Error per test set (paper Fig. 8)")
    assert lines[start + 4] == "| method | outdoor | outdoor + indoor |"
    a_dt = next(line for line in lines[start:] if line.startswith("| a + DT |"))
    frame = pd.read_csv(sweep / "1" / "ood.csv")
    row = frame[frame["in_table"] & (frame["set"] == "indoor")].iloc[0]
    assert f"{row['err_mean_kept']:.2f} ({row['kept_pct']:.0f} %)" in a_dt
    assert (tmp_path / "out" / "ood_sets.png").stat().st_size > 1000
    assert "| outdoor + indoor |" in text.split("## OOD scores on each test set")[1]
    assert "report" in capsys.readouterr().out


def test_the_oracle_row_ranks_by_each_pairs_own_error_and_skips_unreadable_samples(
    tmp_path, caplog
):
    """The fabricated erased pairs have 4x the error of clean ones, so the own-error oracle
    ranks them perfectly (AUROC 1) whatever the DT does (here: chance); a run whose
    ood_samples.csv is not a samples file gets no oracle row and a warning, not a crash."""
    report = {"ood": {"quantiles": [0.75]}}
    _fabricate_run(tmp_path / "a", "a", "bingham", report, separation=0.0)
    _fabricate_run(tmp_path / "b", "a", "chordal", report)
    (tmp_path / "b" / "ood_samples.csv").write_text("x,y\n1,2\n")
    _fabricate_run(tmp_path / "c", "quat", "chordal", report)  # a diverged run: NaN errors
    samples = pd.read_csv(tmp_path / "c" / "ood_samples.csv")
    samples.loc[samples["set"] == "val", "error"] = float("nan")
    samples.to_csv(tmp_path / "c" / "ood_samples.csv", index=False)
    with caplog.at_level("WARNING", logger="rotlearn"):
        runs = [tmp_path / "a", tmp_path / "b", tmp_path / "c"]
        table = pd.read_csv(make_report(runs)["ood_table"])
    oracle = table[table["score"] == "error"]
    assert list(oracle["job"]) == ["a"] and list(oracle["AUROC"]) == [1.0]
    assert table[table["method"] == "a loss=bingham + DT"]["AUROC"].iloc[0] < 0.9
    assert "ood_samples.csv unreadable" in caplog.text and "oracle row" in caplog.text
    assert f"{tmp_path / 'c'}: no oracle row (no finite reference score" in caplog.text
