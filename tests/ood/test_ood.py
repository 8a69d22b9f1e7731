"""OOD scores, thresholds and statistics on hand-made numbers; the callback and rotlearn-eval on a
tiny KITTI-format run."""

from __future__ import annotations

import json
import math
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir

from rotlearn.cli.train import train
from rotlearn.config import ConfigError
from rotlearn.ood import rejection_row
from rotlearn.paths import config_dir
from rotlearn.scores import SCORES
from tests.conftest import (
    tensorboard_events,
    train_tiny_autoencoder,
    write_kitti,
    write_mav,
    yaw_sequence,
)

# -- statistics --------------------------------------------------------------------------------


def test_precision_recall_against_a_hand_computed_example():
    """8 test samples, the last 4 corrupted; keep scores below 0.5 (q = 0.5 of the training)."""
    train = torch.tensor([0.0, 0.2, 0.8, 1.0])  # median 0.5
    scores = torch.tensor([0.1, 0.2, 0.9, 0.3, 0.4, 0.7, 0.8, math.nan])
    errors = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0])
    corrupted = torch.tensor([False] * 4 + [True] * 4)
    row = rejection_row(SCORES["dt"], 0.5, train, scores, errors, corrupted)
    # kept: samples 0, 1, 3 (clean) and 4 (corrupted)
    assert row["threshold"] == pytest.approx(0.5)
    assert row["kept_pct"] == pytest.approx(50.0)
    assert row["precision"] == pytest.approx(75.0)  # 3 of the 4 kept are clean
    assert row["recall"] == pytest.approx(75.0)  # 3 of the 4 clean are kept
    assert row["err_mean_kept"] == pytest.approx((1 + 2 + 4 + 5) / 4)
    assert row["err_mean_all"] == pytest.approx(4.5)
    assert row["nan_scores"] == 1 and row["n_corrupted"] == 4


def test_evaluate_is_a_pure_function_of_predictions_and_flags():
    """No Lightning, no files: a fixed 'network' whose raw output norm is the sample's index."""
    from rotlearn.heads import RotationPrediction
    from rotlearn.ood import evaluate, pr_quantiles, score_sets

    def predict(x):
        raw = torch.zeros(len(x), 4, dtype=torch.float64)
        raw[:, 0] = x[:, 0]
        R = torch.eye(3, dtype=torch.float64).expand(len(x), 3, 3)
        return RotationPrediction(R=R, raw=raw)

    def batches(values, size=3):
        x = torch.tensor(values, dtype=torch.float64)[:, None]
        eye = torch.eye(3, dtype=torch.float64)
        return [{"input": x[i : i + size], "R": eye.expand(len(x[i : i + size]), 3, 3)}
                for i in range(0, len(x), size)]  # fmt: skip

    loaders = {"val": batches([1.0, 2.0, 3.0, 4.0]), "corrupted": batches([0.5, 2.5, 3.5, 5.0])}
    flags = {"corrupted": torch.tensor([True, False, False, False])}
    scores = [SCORES["raw_norm"]]  # kept above its threshold
    frame = evaluate(predict, loaders, flags, scores, [0.75], {"raw_norm": 0.75})
    assert list(frame["set"]) == ["corrupted"] and frame["in_table"].all()
    row = frame.iloc[0]
    assert row["threshold"] == pytest.approx(1.75) and row["kept_pct"] == pytest.approx(75.0)
    assert row["precision"] == pytest.approx(100.0) and row["auroc"] == pytest.approx(1.0)
    sets = score_sets(predict, loaders, flags, scores)
    assert sets["corrupted"]["corrupted"].tolist() == [True, False, False, False]
    assert "corrupted" not in sets["val"] and (sets["val"]["error"] == 0).all()
    assert (frame["thresholds_from"] == "val").all()
    # the paper's protocol: thresholds from the training scores, one argument away
    train_loaders = {"train": loaders["val"], "corrupted": loaders["corrupted"]}
    paper = evaluate(predict, train_loaders, flags, scores, [0.75], reference="train")
    assert paper.iloc[0]["threshold"] == row["threshold"]
    assert paper.iloc[0]["thresholds_from"] == "train"
    with pytest.raises(ValueError, match=r"flags\['corrupted'\] has shape \(2,\)"):
        score_sets(predict, loaders, {"corrupted": torch.zeros(2, dtype=torch.bool)}, scores)
    assert pr_quantiles()[:2] == [0.05, 0.07] and pr_quantiles()[-1] == 0.97


# -- the callback and rotlearn-eval ------------------------------------------------------------

TINY_PAIRS = [
    "data=kitti",
    "data.train_sequences=[01]",
    "data.test_sequences=[00]",
    "data.image_size=16",
    "data.num_workers=0",
    "data.eval_batch_size=4",
    "net.channels=[8,8,8,8]",
    "net.hidden=16",
    "trainer=cpu",
    "trainer.max_epochs=2",
    "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false",
    "callbacks=ood",
    "callbacks.ood.noise_pairs=4",
]


def _write_tiny_kitti(root: Path) -> Path:
    return write_kitti(root, {"00": yaw_sequence(11, 1.0), "01": yaw_sequence(9, -1.0)}, seed=3)


@pytest.fixture
def tiny_kitti(tmp_path):
    return _write_tiny_kitti(tmp_path / "kitti")


@pytest.fixture(scope="module")
def _trained_once(tmp_path_factory):
    """One tiny OOD run for the module's tests (a training is about 5 s); each test gets a
    copy (`trained_run`), so no test sees what another wrote into it."""
    from rotlearn.config import compose as compose_run

    base = tmp_path_factory.mktemp("trained")
    kitti = _write_tiny_kitti(base / "kitti")
    run_dir = base / "run"
    overrides = [f"paths.output_dir={run_dir}", *TINY_PAIRS, f"data.root={kitti}"]
    metrics = train(compose_run(overrides, check=False))
    return run_dir, metrics


@pytest.fixture
def trained_run(tmp_path, tiny_kitti, _trained_once):
    """(a copy of the module's trained run in tmp_path/run, its test metrics); its data root is
    the module's copy of `tiny_kitti`'s frames (the same files)."""
    run_dir, metrics = _trained_once
    return Path(shutil.copytree(run_dir, tmp_path / "run", symlinks=True)), dict(metrics)


def test_the_callback_writes_every_column(trained_run):
    run_dir, _ = trained_run
    frame = pd.read_csv(run_dir / "ood.csv")
    expected = {
        "rep", "set", "in_table", "score", "keep", "q", "threshold", "n", "n_corrupted",
        "nan_scores", "kept_pct", "err_mean_all", "err_median_all", "err_mean_kept",
        "err_median_kept", "precision", "recall", "auroc", "spearman",
    }  # fmt: skip
    assert expected <= set(frame.columns)
    assert set(frame["score"]) == {"dt", "eigengap", "raw_norm"}  # no auto-encoder checkpoint
    assert set(frame["set"]) == {"clean", "corrupted"}
    assert sorted(frame["q"].unique()) == [0.25, 0.5, 0.75, 1.0]
    assert (frame[frame["set"] == "corrupted"]["n_corrupted"] == 5).all()  # last half of 10
    assert (frame[frame["set"] == "clean"]["n_corrupted"] == 0).all()
    table = (run_dir / "ood.md").read_text()
    assert "| a + DT | 0.75 |" in table
    assert "DT at the paper's q = 0.75, even where other quantiles were asked" in table  # why
    # TensorBoard: one figure per score and the example pairs; each AUROC a result, no
    # per-quantile scalars
    (test,) = [e for name, e in tensorboard_events(run_dir).items() if name.endswith("/test")]
    assert {"ood/dt", "ood/eigengap", "ood/raw_norm", "ood/examples"} <= set(test.Tags()["images"])
    assert {t for t in test.Tags()["scalars"] if t.startswith("ood/")} == {
        "ood/auroc_dt", "ood/auroc_eigengap", "ood/auroc_raw_norm"}  # fmt: skip


def _eval_cfg(overrides, out):
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("eval", overrides=[f"paths.output_dir={out}", *overrides])


def test_rotlearn_eval_reproduces_the_test_error(trained_run, tmp_path, monkeypatch):
    """...and writes its metrics.json once: the run's records and the evaluation's facts (the
    checkpoint, the temperature) in one file, as `evaluate` returns it."""
    import rotlearn.io
    import rotlearn.lit.records
    from rotlearn.cli.evaluate import evaluate

    written, write = [], rotlearn.io.write_json_atomic

    def counted(path, *args, **kwargs):
        written.append(Path(path).name)
        return write(path, *args, **kwargs)

    monkeypatch.setattr(rotlearn.io, "write_json_atomic", counted)
    monkeypatch.setattr(rotlearn.lit.records, "write_json_atomic", counted)
    run_dir, metrics = trained_run
    out = tmp_path / "eval"
    result = evaluate(_eval_cfg([f"ckpt={run_dir}", "ood.quantiles=[0.5]"], out))
    assert result["test/err_mean"] == pytest.approx(metrics["test/err_mean"], rel=1e-6)
    frame = pd.read_csv(out / "ood.csv")
    assert set(frame["q"]) == {0.5, 0.75}  # the asked quantile and DT's Table I quantile
    assert written.count("metrics.json") == 1
    on_disk = json.loads((out / "metrics.json").read_text())
    assert set(on_disk) == set(result) and on_disk["rep"] == "a" and on_disk["temperature"] > 0
    assert Path(on_disk["ckpt"]).parent.parent == Path(run_dir).resolve()
    assert on_disk["seed"] == metrics["seed"]  # a fact of the run's records
    assert "epochs" not in on_disk and "tested_weights" not in on_disk  # no fitting here
    assert not (run_dir / "ood.csv").stat().st_mtime > (out / "ood.csv").stat().st_mtime


def test_rotlearn_eval_of_several_runs_scores_their_ensemble(trained_run, tiny_kitti, make_cfg,
                                                             tmp_path):  # fmt: skip
    """ckpt=[run, run]: the ensemble's own calibration is fitted on validation, and its DT and
    the members' disagreement are OOD scores."""
    from rotlearn.cli.evaluate import evaluate

    run_dir, _ = trained_run
    other = tmp_path / "seed1"
    train(make_cfg([*TINY_PAIRS, f"data.root={tiny_kitti}", "seed=1"], run_dir=other))
    out = tmp_path / "eval"
    result = evaluate(_eval_cfg([f"ckpt=[{run_dir},{other}]", "ood.quantiles=[0.5]"], out))
    assert result["rep"] == "ensemble" and len(result["members"]) == 2
    assert result["calibration/temperature"] == pytest.approx(result["temperature"], rel=1e-6)
    assert "test/disagreement_spearman" in result and "test/ece" in result
    frame = pd.read_csv(out / "ood.csv")
    assert {"dt", "eigengap", "raw_norm", "disagreement"} <= set(frame["score"])
    assert (frame[frame["score"] == "disagreement"]["nan_scores"] == 0).all()
    # nothing is trained, so nothing is checkpointed: no stray checkpoints/ with the ensemble's
    # temperature.json and ood_thresholds.json below tensorboard/ (Lightning's default folder)
    assert not list(out.rglob("checkpoints")) and not list(out.rglob("*thresholds*"))
    # what was evaluated, as a run config (rotlearn-report reads it; tests/report/test_runs.py)
    evaluated = yaml.safe_load((out / "evaluated.yaml").read_text())
    assert evaluated["evaluated"] == {"members": 2} and evaluated["rep"]["name"] == "a"
    assert evaluated["model"]["_target_"] == "rotlearn.lit.RotationRegressor"
    assert evaluated["callbacks"]["ood"]["quantiles"] == [0.5]  # the evaluation's own setting


def test_the_rotlearn_eval_command_checks_the_run_then_evaluates_it(
    trained_run, tmp_path, monkeypatch
):
    """The command line passes its checks (a data key eval.yaml does not list needs no `+`) and
    evaluates the run where hydra.run.dir says."""
    from rotlearn.cli.evaluate import main

    run_dir, metrics = trained_run
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "eval"
    args = [f"ckpt={run_dir}", "ood.quantiles=[0.5]", "data.batch_size=4", f"hydra.run.dir={out}"]
    monkeypatch.setattr(sys, "argv", ["rotlearn-eval", *args])
    main()
    evaluated = json.loads((out / "metrics.json").read_text())
    assert evaluated["test/err_median"] == pytest.approx(metrics["test/err_median"], rel=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval", "kitti", "run"]  # nothing else


def test_an_evaluation_with_an_unlisted_key_never_writes_into_an_existing_directory(
    trained_run, tmp_path, monkeypatch
):
    """The existing-directory refusal sees the arguments Hydra runs: with a data key eval.yaml
    does not list (it gets its `+`), an existing, non-empty hydra.run.dir is refused too."""
    from rotlearn.cli.evaluate import _checked

    run_dir, _ = trained_run
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "taken"
    out.mkdir()
    (out / "precious.txt").write_text("keep")
    args = [f"ckpt={run_dir}", "data.batch_size=4", f"hydra.run.dir={out}"]
    with pytest.raises(SystemExit, match="already exists and is not empty") as refused:
        _checked(args)
    assert "ckpt_path" not in str(refused.value)  # no resume advice: evaluations do not resume
    assert [p.name for p in out.iterdir()] == ["precious.txt"]


def test_the_rotlearn_eval_command_takes_a_list_of_runs_and_names_a_missing_member(
    trained_run, tmp_path, monkeypatch
):
    """`rotlearn-eval ckpt=[<run>,<run>]` (make reproduce-ood's ensembles) passes the command
    line's checks member by member; a member that is not a run is named, nothing written."""
    from rotlearn.cli.evaluate import _checked

    run_dir, _ = trained_run
    monkeypatch.chdir(tmp_path)
    copy = shutil.copytree(run_dir, tmp_path / "copy")  # another run (the same one is refused)
    args = [f"ckpt=[{run_dir},{copy}/checkpoints/last.ckpt]", f"hydra.run.dir={tmp_path / 'e'}"]
    assert _checked(args) == args
    missing = tmp_path / "nowhere"
    refusal = re.escape(f"ckpt: no checkpoint at {missing} (nothing was written)")
    with pytest.raises(SystemExit, match=refusal):
        _checked([f"ckpt=[{run_dir},{missing}]", f"hydra.run.dir={tmp_path / 'e'}"])
    assert not (tmp_path / "e").exists()


def test_an_ensemble_of_runs_that_take_other_input_is_refused_before_anything_is_written(
    trained_run, tiny_kitti, make_cfg, tmp_path, monkeypatch
):
    """The ensemble reads the first member's data; a member trained on frames normalised
    otherwise (or of another size, or another dataset) would be fed inputs it never saw:
    silently wrong, or a shape error after the evaluation's directory was made."""
    from rotlearn.cli.evaluate import _checked

    run_dir, _ = trained_run
    other = tmp_path / "normalised"
    train(make_cfg([*TINY_PAIRS, f"data.root={tiny_kitti}", "data.mean=0.5"], run_dir=other))
    monkeypatch.chdir(tmp_path)
    refusal = (
        f"rotlearn-eval: config key ckpt: {other}/checkpoints/last.ckpt was trained with "
        f"data.mean=0.5, {run_dir}/checkpoints/last.ckpt with 0.0; an ensemble's members must "
        "take the same input (nothing was written)"
    )
    with pytest.raises(SystemExit, match=re.escape(refusal)):
        _checked([f"ckpt=[{run_dir},{other}]", f"hydra.run.dir={tmp_path / 'e'}"])
    assert not (tmp_path / "e").exists()


def test_rotlearn_eval_sweeps_over_runs_with_m(trained_run, tmp_path, monkeypatch):
    """`rotlearn-eval -m ckpt=<run>,<run>` is one evaluation per run (Hydra's sweep); it was
    refused as "no checkpoint at <run>,<run>". Each run is checked to exist and the first job's
    config validated before anything is written; without -m the sweep is named for what it is."""
    from rotlearn.cli.evaluate import _checked

    run_dir, _ = trained_run
    monkeypatch.chdir(tmp_path)
    copy = shutil.copytree(run_dir, tmp_path / "copy")
    out = f"hydra.sweep.dir={tmp_path / 'e'}"
    assert _checked(["-m", f"ckpt={run_dir},{copy}", out]) == ["-m", f"ckpt={run_dir},{copy}", out]
    with pytest.raises(SystemExit, match=re.escape(f"ckpt: no checkpoint at {tmp_path / 'gone'}")):
        _checked(["-m", f"ckpt={run_dir},{tmp_path / 'gone'}", out])
    with pytest.raises(SystemExit, match=r"config key data\.root: no directory .*nowhere"):
        _checked(["-m", f"ckpt={run_dir},{copy}", f"data.root={tmp_path / 'nowhere'}", out])
    with pytest.raises(SystemExit, match=r"is a sweep: add -m for one evaluation per run, or "):
        _checked([f"ckpt={run_dir},{copy}", f"hydra.run.dir={tmp_path / 'e'}"])
    assert not (tmp_path / "e").exists()


def test_the_ood_settings_of_an_evaluation_are_named_as_it_takes_them(
    trained_run, tmp_path, monkeypatch
):
    """eval.yaml's `ood.<key>` is merged into the run's `callbacks.ood`: a misspelt one was
    answered with "did you mean callbacks.ood.quantiles?", which rotlearn-eval then took (with
    Hydra's `+`) and ignored. Both are named as rotlearn-eval takes them, nothing written."""
    from rotlearn.cli.evaluate import _checked

    run_dir, _ = trained_run
    monkeypatch.chdir(tmp_path)
    out = f"hydra.run.dir={tmp_path / 'e'}"
    with pytest.raises(SystemExit, match=r"^rotlearn-eval: config key ood\.quantile: unknown key; "
                       r"did you mean ood\.quantiles\?; allowed: quantiles, "):  # fmt: skip
        _checked([f"ckpt={run_dir}", "ood.quantile=[0.5]", out])
    refusal = (r"^rotlearn-eval: config key callbacks: unknown key; allowed: ckpt, data, "
               r"expect_rep, hydra, ood, paths, sweep, trainer; ood\.quantiles sets the run's "
               r"callbacks\.ood\.quantiles \(nothing was written\)$")  # fmt: skip
    for typed in ("callbacks.ood.quantiles=[0.5]", "+callbacks.ood.quantiles=[0.5]"):
        with pytest.raises(SystemExit, match=refusal):
            _checked([f"ckpt={run_dir}", typed, out])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kitti", "run"]  # no "e"


def test_an_ensemble_without_its_data_is_refused_before_anything_is_written(
    trained_run, tmp_path, monkeypatch
):
    """A single run's evaluation checked its data folder first; an ensemble's built the Trainer,
    failed in the datamodule and left a FAILED evaluation directory."""
    from rotlearn.cli.evaluate import _checked

    run_dir, _ = trained_run
    monkeypatch.chdir(tmp_path)
    copy = shutil.copytree(run_dir, tmp_path / "copy")
    gone = tmp_path / "gone"
    refusal = f"rotlearn-eval: config key data.root: no directory {gone}; it must hold "
    with pytest.raises(SystemExit, match=re.escape(refusal)):
        _checked(
            [f"ckpt=[{run_dir},{copy}]", f"data.root={gone}", f"hydra.run.dir={tmp_path / 'e'}"]
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy", "kitti", "run"]  # no "e"


def test_rotlearn_eval_refuses_bad_input(trained_run, tmp_path):
    from rotlearn.cli.evaluate import evaluate

    run_dir, _ = trained_run
    with pytest.raises(ConfigError, match=r"config key ckpt: .*nowhere.*no checkpoint"):
        evaluate(_eval_cfg([f"ckpt={tmp_path / 'nowhere'}"], tmp_path / "e1"))
    with pytest.raises(ConfigError, match="trained with rep=a, not expect_rep=sixd"):
        evaluate(_eval_cfg([f"ckpt={run_dir}", "expect_rep=sixd"], tmp_path / "e2"))
    with pytest.raises(ConfigError, match=r"callbacks\.ood\.quantiles: should be less than or "
                       r"equal to 1 \(at \[1\]\), got \[0\.5, 1\.5\]"):  # fmt: skip
        evaluate(_eval_cfg([f"ckpt={run_dir}", "ood.quantiles=[0.5,1.5]"], tmp_path / "e3"))


def test_nan_scores_are_counted_in_the_csv(tiny_kitti, make_cfg, tmp_path, monkeypatch):
    """A score that is NaN for some samples is reported in nan_scores and never kept."""
    from rotlearn import scores as scores_module

    def raw_norm_with_nans(prediction):
        values = torch.linalg.vector_norm(prediction.raw, dim=-1)
        return torch.where(torch.arange(len(values)) % 2 == 0, math.nan, values)

    patched = scores_module.Score("raw_norm", False, raw_norm_with_nans)
    monkeypatch.setitem(scores_module.SCORES, "raw_norm", patched)
    run_dir = tmp_path / "run"
    overrides = [*TINY_PAIRS, f"data.root={tiny_kitti}", "rep=sixd", "data.val_fraction=0.4"]
    train(make_cfg(overrides, run_dir=run_dir))  # 3 validation pairs: the middle one finite
    frame = pd.read_csv(run_dir / "ood.csv")
    rows = frame[frame["score"] == "raw_norm"]
    assert (rows["nan_scores"] == 5).all()  # 10 test pairs, batches of 4: indices 0, 2 of each
    assert (rows["kept_pct"] <= 50.0).all()
    assert np.isfinite(rows["threshold"]).all()


def test_an_autoencoder_trained_as_its_own_run_scores_the_pairs(tiny_kitti, make_cfg, tmp_path):
    """The auto-encoder trains as its own run (`experiment=kitti_autoencoder`); the OOD
    evaluation only reads its checkpoint, and trains nothing inside the test."""
    ae_run = train_tiny_autoencoder(tiny_kitti, tmp_path / "ae")
    run_dir = tmp_path / "run"
    overrides = [*TINY_PAIRS, f"data.root={tiny_kitti}", "rep=sixd", "trainer.max_epochs=1",
                 f"callbacks.ood.autoencoder_ckpt={ae_run}"]  # fmt: skip
    train(make_cfg(overrides, run_dir=run_dir))
    frame = pd.read_csv(run_dir / "ood.csv")
    assert set(frame["score"]) == {"raw_norm", "autoencoder"}  # no eigenvalues for 6D
    ae = frame[frame["score"] == "autoencoder"]
    assert set(ae["q"]) == {0.25, 0.5, 0.75, 1.0} and (ae["nan_scores"] == 0).all()
    assert not (run_dir / "autoencoder.ckpt").exists()  # nothing trained here
    assert "| sixd + AE | 1.00 |" in (run_dir / "ood.md").read_text()
    # a rotation run's checkpoint is no auto-encoder: refused, naming it
    with pytest.raises(ValueError, match="not an auto-encoder checkpoint"):
        train(make_cfg([*overrides[:-1], f"callbacks.ood.autoencoder_ckpt={run_dir}"],
                       run_dir=tmp_path / "again"))  # fmt: skip


def test_the_report_collects_table_one(trained_run, make_cfg, tmp_path):
    from omegaconf import OmegaConf

    from rotlearn.report import make_report

    run_dir, _ = trained_run
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(make_cfg(TINY_PAIRS), run_dir / ".hydra" / "config.yaml")
    files = make_report(run_dir, tmp_path / "report")
    report = files["report"].read_text()
    assert "## OOD rejection (paper Table I)" in report
    table = pd.read_csv(files["ood_table"])
    assert list(table["method"]) == ["a", "a + DT", "a + gap", "a + norm", "a + own error (oracle)"]
    assert (table["clean kept %"] <= 100).all()
    # the oracle keeps the pairs whose own error is below the DT row's quantile of the errors of
    # the set the thresholds come from, and the paper comparison leaves it out
    oracle, dt = table.iloc[-1], table[table["method"] == "a + DT"].iloc[0]
    samples = pd.read_csv(run_dir / "ood_samples.csv")
    reference = pd.read_csv(run_dir / "ood.csv")["thresholds_from"].iloc[0]
    threshold = np.quantile(samples[samples["set"] == reference]["error"], float(dt["q"]))
    clean = samples[samples["set"] == "clean"]["error"]
    assert oracle["q"] == dt["q"] and oracle["score"] == "error"
    assert oracle["clean kept %"] == pytest.approx(100 * (clean < threshold).mean())


def tiny_mav_overrides(root) -> list[str]:
    """A tiny MAV-format run (18 -> 16 pixel frames, 30 % test pairs) with TINY_PAIRS' net,
    trainer and OOD settings, on the MAV data at `root`."""
    return [
        "data=mav",
        f"data.root={root}",
        "data.resize=18",
        "data.image_size=16",
        "data.test_fraction=0.3",
        *[o for o in TINY_PAIRS if not o.startswith("data")],
        "data.num_workers=0",
    ]


def test_unseen_scenes_count_as_ood(tmp_path, make_cfg):

    run_dir = tmp_path / "run"
    overrides = [
        *tiny_mav_overrides(write_mav(tmp_path / "mav", frames=30)),
        "data.test_scenes=[outdoor,indoor]",
        "callbacks.ood.unseen_scenes_ood=true",
    ]
    train(make_cfg(overrides, run_dir=run_dir))
    frame = pd.read_csv(run_dir / "ood.csv")
    clean = frame[frame["set"] == "clean"]
    # indoor holds frames 20-29: 9 pairs, of which round(0.3 * 9) = 3 are test pairs
    assert (clean["n_corrupted"] == 3).all() and (clean["n"] == 6).all()


def test_ood_config_keys_are_checked_before_training(make_cfg, on_disk):
    from rotlearn.config import validate

    validate(on_disk(make_cfg(["experiment=kitti_ood_demo"])))
    ood = ["data=kitti", "callbacks=ood"]
    with pytest.raises(ConfigError, match=r"callbacks\.ood\.quantile: unknown key; did you mean"):
        validate(on_disk(make_cfg([*ood, "+callbacks.ood.quantile=[0.5]"])))
    with pytest.raises(ConfigError, match=r"callbacks\.ood\.noise_pairs: should be a valid int"):
        validate(on_disk(make_cfg([*ood, "callbacks.ood.noise_pairs=many"])))
    with pytest.raises(ConfigError, match=r"callbacks\.ood\.examples: should be greater than or"):
        validate(on_disk(make_cfg([*ood, "callbacks.ood.examples=-1"])))
    with pytest.raises(ConfigError, match=r"callbacks\.ood: needs an image-pair datamodule"):
        validate(make_cfg(["callbacks=ood"]))  # synthetic data: nothing to erase


def test_calibrated_threshold_gives_keep_flags_for_image_pairs(trained_run, tiny_kitti, capsys):
    from rotlearn import load
    from rotlearn.cli.predict import main as predict

    run_dir, _ = trained_run
    frame = pd.read_csv(run_dir / "ood.csv")
    row = frame[(frame["score"] == "dt") & frame["in_table"] & (frame["set"] == "clean")]
    assert (run_dir / "checkpoints" / "ood_thresholds.json").is_file()
    predictor = load(run_dir)
    assert predictor.ood["q"] == 0.75 and predictor.ood["reference"] == "val"
    assert predictor.ood["threshold"] == pytest.approx(float(row["threshold"].iloc[0]))
    frames = sorted((tiny_kitti / "sequences" / "00" / "image_2").glob("*.png"))
    assert predict([str(run_dir), str(frames[0]), str(frames[1])]) == 0
    said = capsys.readouterr().out  # where the threshold came from: validation, by default
    assert "quantile of the validation scores; lower = more confident" in said
    assert predict([str(run_dir), str(frames[0]), str(frames[1]), "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert set(answer) >= {"R", "q_xyzw", "dt_score", "dispersion", "keep"}
    assert answer["ood"]["reference"] == "val"
    assert answer["keep"] == (answer["dt_score"] < predictor.ood["threshold"])
    assert predict([str(run_dir), str(frames[0])]) == 2  # an image model needs two frames
    assert "two image files" in capsys.readouterr().err
    for name in ("last.ckpt", "best.ckpt"):  # a received run whose data config does not build
        checkpoint = torch.load(run_dir / "checkpoints" / name, weights_only=True)
        checkpoint["rotlearn_config"]["data"]["mean"] = "x"
        torch.save(checkpoint, run_dir / "checkpoints" / name)
    assert predict([str(run_dir), str(frames[0]), str(frames[1])]) == 2  # was a traceback
    said = capsys.readouterr().err
    assert said.startswith(f"rotlearn-predict: {run_dir}: its data config does not build: ")
    assert said.count("\n") == 1 and "could not convert string to float: 'x'" in said, said
    with pytest.raises(ValueError, match=r"shape \(B, 6, 16, 16\)"):
        predictor(torch.zeros(1, 6, 8, 8))
