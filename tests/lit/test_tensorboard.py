"""What a person sees in TensorBoard, read from the event files of real runs (rotlearn-train in a
subprocess, umask 022): the learning curves against the epoch and few cards, the runs named by
their overrides, an HPARAMS record of what the user set with the test results as its metrics,
one text table, no library noise on the console, and every file readable by the group."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from tensorboard.plugins.hparams import metadata

from tests.conftest import (
    FAST,
    modes,
    run_cli,
    scalar_tags,
    tensorboard_events,
    train_tiny_autoencoder,
    write_kitti,
    yaw_sequence,
)

# What a normal run must not print: library warnings and tips nobody running rotlearn can act on.
LIBRARY_NOISE = (
    "Metric `SpearmanCorrcoef` will save all targets",  # torchmetrics, at the model's construction
    "try installing [litlogger]",  # Lightning's cloud adverts
    "try installing [litmodels]",
    "`isinstance(treespec, LeafSpec)` is deprecated",  # Lightning's use of torch's _pytree
    "FLOPs",  # the model summary's column of zeros
    "Total Flops",
    "will override existing callbacks",  # DataDependentInit seen again by trainer.test
)
CURVES = {"error/mean", "error/median", "error/p10", "error/p90", "learning/loss", "learning/lr",
          "learning/epoch_time_s"}  # fmt: skip
RESULTS = {"test/err_vs_identity", "test/nll", "test/ece"}  # one-shot: the test sub-run only
PLUMBING = ("callbacks", "logger", "hydra", "paths", "ckpt_path")


def _session(events) -> dict:
    """The HPARAMS session start of a TensorBoard run: {hparam: python value}."""
    content = events.PluginTagToContent(metadata.PLUGIN_NAME)
    start = metadata.parse_session_start_info_plugin_data(content[metadata.SESSION_START_INFO_TAG])
    return {k: getattr(v, v.WhichOneof("kind")) for k, v in start.hparams.items()}


def _check_layout(run: Path, name: str, epochs: int) -> dict:
    """The run's TensorBoard folder holds one run named `name` with train, val and test
    sub-runs; every curve has one point per epoch, the test values one point at the end.
    Returns {sub-run: events}."""
    events = tensorboard_events(run)
    assert set(events) == {f"{name}/train", f"{name}/val", f"{name}/test"}
    stages = {k.rsplit("/", 1)[1]: v for k, v in events.items()}
    for stage in ("train", "val"):
        for tag in stages[stage].Tags()["scalars"]:
            assert [e.step for e in stages[stage].Scalars(tag)] == list(range(1, epochs + 1)), tag
    for tag in stages["test"].Tags()["scalars"]:
        assert [e.step for e in stages["test"].Scalars(tag)] == [epochs], tag
    assert set(stages["val"].Tags()["scalars"]) == {"error/mean", "error/median", "error/p10",
                                                    "error/p90", "learning/loss"}  # fmt: skip
    return stages


def test_a_default_run_opens_on_its_curves_and_compares_by_what_it_set(tmp_path):
    run = tmp_path / "run"
    fast = [a for a in FAST if not a.startswith("trainer.enable_progress_bar")]
    args = [*fast, "trainer.max_epochs=3", "optim.lr=2e-3", f"hydra.run.dir={run}"]
    result = run_cli(args, tmp_path, umask=0o022, warnings=True)
    assert result.returncode == 0, result.stderr[-3000:]
    printed = result.stdout + result.stderr
    for noise in LIBRARY_NOISE:
        assert noise not in printed, noise
    assert printed.count("Trainable params") == 1
    assert "loss=" in printed and "val err=" in printed  # the progress bar
    # at most 12 cards: the curves and three one-shot results; nothing one-dot per quantile
    assert scalar_tags(run) == CURVES | RESULTS and len(CURVES | RESULTS) <= 12
    name = "data=tiny,trainer=cpu,net.point_channels=[16,32,64],net.head_channels=[32,16],"
    name += "trainer.max_epochs=3,optim.lr=0.002"  # its overrides, in their shortest form
    stages = _check_layout(run, name, epochs=3)
    hparams = _session(stages["test"])
    assert hparams["optim.lr"] == 0.002 and hparams["trainer.max_epochs"] == 3
    assert hparams["data"] == "tiny" and hparams["trainer"] == "cpu" and hparams["rep"] == "a"
    assert hparams["loss"] == "chordal" and hparams["net"] == "pointnet" and hparams["seed"] == 0
    assert hparams["net.point_channels"] == "[16,32,64]"
    assert not any(k.split(".")[0] in PLUMBING for k in hparams)
    assert not any(k.startswith("callbacks") for k in hparams)
    # its metrics: the scalars of the session's run, the test results
    metrics = json.loads((run / "metrics.json").read_text())
    test = stages["test"]
    assert set(test.Tags()["scalars"]) == {"error/mean", "error/median", *RESULTS}
    assert test.Scalars("error/mean")[0].value == pytest.approx(metrics["test/err_mean"], rel=1e-6)
    assert test.Scalars("test/ece")[0].value == pytest.approx(metrics["test/ece"], rel=1e-6)
    assert "results" in "".join(test.Tags()["tensors"])  # the text table
    assert test.Tags()["images"] == ["test/reliability"]
    # every file the run wrote is readable by all, every folder enterable (umask 022)
    written = modes(run)
    wrong = {p: oct(m) for p, m in written.items() if m != (0o755 if (run / p).is_dir() else 0o644)}
    assert written and not wrong, wrong


def test_the_best_weights_results_stand_at_their_own_epoch(tmp_path):
    """With test_ckpt=best the test scores an earlier epoch's weights: its points stand at that
    epoch, not at the last (where they read as the last weights' results), and metrics.json
    says how many epochs the tested weights trained. best.ckpt is considered every 2nd epoch
    here, so of 3 epochs the tested weights are the 2nd's whatever the errors."""
    run = tmp_path / "run"
    best_every_2nd = "callbacks.checkpoint.every_n_epochs=2"
    args = [*FAST, "trainer.max_epochs=3", "test_ckpt=best", best_every_2nd, f"hydra.run.dir={run}"]
    result = run_cli(args, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["epochs"], metrics["tested_epochs"], metrics["tested_checkpoint"]) == (
        3, 2, "best.ckpt")  # fmt: skip
    assert "test error (a head, best weights of epoch 2/3): mean" in result.stdout + result.stderr
    stages = {k.rsplit("/", 1)[1]: v for k, v in tensorboard_events(run).items()}
    assert [e.step for e in stages["val"].Scalars("error/mean")] == [1, 2, 3]
    for tag in stages["test"].Tags()["scalars"]:
        assert [e.step for e in stages["test"].Scalars(tag)] == [2], tag
    assert [e.step for e in stages["test"].Images("test/reliability")] == [2]  # its figure too


def test_an_ood_run_adds_each_scores_auroc_and_nothing_per_quantile(tmp_path):
    kitti = write_kitti(tmp_path / "kitti", {"00": yaw_sequence(11, 1.0),
                                             "01": yaw_sequence(9, -1.0)}, seed=3)  # fmt: skip
    run = tmp_path / "run"
    args = ["data=kitti", f"data.root={kitti}", "data.train_sequences=[01]",
            "data.test_sequences=[00]", "data.image_size=16", "data.num_workers=0",
            "data.eval_batch_size=4", "net.channels=[8,8,8,8]", "net.hidden=16", "trainer=cpu",
            "trainer.max_epochs=2", "trainer.enable_progress_bar=false", "callbacks=ood",
            "callbacks.ood.noise_pairs=4", "calibrate=true",
            f"callbacks.ood.autoencoder_ckpt={train_tiny_autoencoder(kitti, tmp_path / 'ae')}",
            f"hydra.run.dir={run}"]  # fmt: skip
    result = run_cli(args, tmp_path, umask=0o022)
    assert result.returncode == 0, result.stderr[-3000:]
    aurocs = {f"ood/auroc_{s}" for s in ("dt", "eigengap", "raw_norm", "autoencoder")}
    tags = scalar_tags(run)
    assert tags == CURVES | RESULTS | aurocs and len(tags) <= 16
    (name,) = [p.name for p in (run / "tensorboard").iterdir()]
    assert name.startswith("data=kitti,data.root=kitti,") and "callbacks" not in name
    assert len(name) <= 120  # a long command line: cut, and told apart by a hash
    stages = _check_layout(run, name, epochs=2)
    hparams = _session(stages["test"])
    assert hparams["data"] == "kitti" and hparams["calibrate"] is True and hparams["rep"] == "a"
    assert not any(k.split(".")[0] in PLUMBING for k in hparams)
    images = set(stages["test"].Tags()["images"])
    assert {"test/reliability", "ood/dt", "ood/autoencoder", "ood/examples"} <= images
    metrics = json.loads((run / "metrics.json").read_text())
    for tag in aurocs:
        assert stages["test"].Scalars(tag)[0].value == pytest.approx(metrics[tag], rel=1e-6)
    # the run's files and the dataset's frame cache are readable by all (umask 022)
    for root in (run, kitti / ".rotlearn_cache"):
        written = modes(root)
        wrong = {p: oct(m) for p, m in written.items()
                 if m != (0o755 if (root / p).is_dir() else 0o644)}  # fmt: skip
        assert written and not wrong, wrong
    assert {"ood.csv", "ood.md", "ood_samples.csv", "ood_examples.png"} <= {
        p.name for p in run.iterdir()}  # fmt: skip
    assert (run / "checkpoints" / "temperature.json").is_file()
