"""`calibrate`: the temperature and the level map fitted on the validation set at test start."""

from __future__ import annotations

import json
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch

import rotlearn
from rotlearn.bingham import LevelMap, fit_temperature
from rotlearn.checkpoint import TEMPERATURE_FILE, read_temperature
from rotlearn.cli.train import ConfigError, build, train
from rotlearn.lit.calibration import PostHocCalibration, validation_beliefs
from tests.conftest import FAST

RUN = ["rep=a", *FAST, "trainer.max_epochs=1", "logger=csv", "calibrate=true"]


class _SeesTheTemperature(pl.Callback):
    """Records the module's temperature when the test starts and ends (as the OOD evaluation,
    which runs at the test's end, would see it)."""

    def __init__(self) -> None:
        self.seen: dict[str, float | None] = {}

    def on_test_start(self, trainer, pl_module) -> None:
        self.seen["start"] = getattr(pl_module, "belief_temperature", None)

    def on_test_end(self, trainer, pl_module) -> None:
        self.seen["end"] = getattr(pl_module, "belief_temperature", None)


def test_a_calibrated_run_writes_logs_and_sets_the_temperature(make_cfg):
    cfg = make_cfg(RUN)
    model, datamodule, trainer = build(cfg)
    spy = _SeesTheTemperature()
    trainer.callbacks.insert(0, spy)  # before PostHocCalibration: the hook order still holds
    trainer.fit(model, datamodule=datamodule)
    trainer.test(model, datamodule=datamodule, verbose=False)
    run = Path(cfg.paths.output_dir)
    record = read_temperature(run / "checkpoints" / TEMPERATURE_FILE)
    assert record is not None and record["checkpoint"] == "last.ckpt"
    assert record["num_val"] == 16  # data=tiny's validation set
    t = record["temperature"]
    assert t > 0 and model.belief_temperature == t
    assert spy.seen["end"] == t  # what an on_test_end callback (the OOD evaluation) sees
    assert record["val_nll"] <= record["val_nll_uncalibrated"] + 1e-9
    # the same fit, redone from the tested weights and the validation set
    A, q = validation_beliefs(model, datamodule)
    assert A.shape == (16, 4, 4) and q.shape == (16, 4)
    assert float(fit_temperature(A, q).temperature) == pytest.approx(t, rel=1e-9)
    # results of the run (metrics.json): in the metrics of the test; not a per-epoch series
    metrics = trainer.callback_metrics
    assert float(metrics["calibration/temperature"]) == pytest.approx(t, rel=1e-6)
    assert float(metrics["calibration/val_nll"]) == pytest.approx(record["val_nll"], rel=1e-6)
    assert "calibration/temperature" not in (run / "csv" / "metrics.csv").read_text()
    # the level map: fitted with T, saved with it, used by the test metrics
    assert isinstance(model.belief_levels, LevelMap)
    assert model.belief_levels.masses.tolist() == record["credible_masses"]
    assert len(record["credible_masses"]) == 21
    assert {"test/ece", "test/tempered_ece", "test/uncalibrated_ece"} <= set(metrics)
    # testing again fits again from the untempered belief: the same T, not T^2, the same map
    trainer.test(model, datamodule=datamodule, verbose=False)
    assert model.belief_temperature == pytest.approx(t, rel=1e-12)
    assert model.belief_levels.masses.tolist() == record["credible_masses"]


def test_the_record_names_the_tested_checkpoint_and_reaches_metrics_json(make_cfg):
    cfg = make_cfg([*RUN, "test_ckpt=best"])
    metrics = train(cfg)
    run = Path(cfg.paths.output_dir)
    record = json.loads((run / "checkpoints" / TEMPERATURE_FILE).read_text())
    assert record["checkpoint"] == "best.ckpt"
    assert set(record) == {"temperature", "checkpoint", "val_nll", "val_nll_uncalibrated",
                           "num_val", "credible_masses"}  # fmt: skip
    on_disk = json.loads((run / "metrics.json").read_text())
    assert on_disk["calibration/temperature"] == pytest.approx(record["temperature"], rel=1e-6)
    assert metrics["tested_weights"] == "best" and metrics["tested_checkpoint"] == "best.ckpt"
    # the run directory loads those weights, tempered by what was fitted for them
    loaded = rotlearn.load(run)
    assert loaded.temperature == pytest.approx(record["temperature"], rel=1e-12)


def test_calibration_is_refused_for_a_head_without_a_belief(make_cfg, on_disk, tmp_path):
    from rotlearn.config import command_line

    with pytest.raises(ConfigError, match=r"config key calibrate: .*rep=sixd has none"):
        build(make_cfg(["rep=sixd", *FAST, "calibrate=true"]))
    # rotlearn-train checks the command line this way before Hydra makes the run directory
    with pytest.raises(ConfigError, match=r"config key calibrate: .*rep=quat has none"):
        command_line(["rep=quat", "calibrate=true"], str(tmp_path / "run"))
    assert not (tmp_path / "run").exists()
    with pytest.raises(ConfigError, match=r"calibrate: .*AutoEncoderModule has no head"):
        build(on_disk(make_cfg(["experiment=kitti_autoencoder", "calibrate=true"])))
    with pytest.raises(ConfigError, match="calibrate"):
        PostHocCalibration("x").setup(None, torch.nn.Module(), "test")


def test_calibrate_must_be_a_boolean_or_auto(make_cfg):
    with pytest.raises(ConfigError, match="calibrate"):
        build(make_cfg(["rep=a", *FAST, "calibrate=maybe"]))


def _calibrates(trainer) -> list[PostHocCalibration]:
    return [cb for cb in trainer.callbacks if isinstance(cb, PostHocCalibration)]


def test_auto_calibrates_every_belief_head_and_nothing_else(make_cfg):
    """No flag: a belief head (chordal or likelihood loss) is calibrated, a 6D head is not."""
    for overrides, expected in ((["rep=a"], 1), (["rep=a", "loss=bingham"], 1),
                                (["rep=fisher", "loss=fisher_nll"], 1), (["rep=sixd"], 0),
                                (["rep=a", "calibrate=false"], 0)):  # fmt: skip
        _, _, trainer = build(make_cfg([*FAST, *overrides]))
        found = _calibrates(trainer)
        assert len(found) == expected, overrides
        assert all(not cb.required for cb in found)  # auto: never required


def test_auto_without_a_validation_set_tests_uncalibrated_and_true_refuses(make_cfg, caplog):
    from rotlearn.lit.regressor import RotationRegressor

    class NoValidation(pl.LightningDataModule):
        def val_dataloader(self):
            return []

    module = RotationRegressor.__new__(RotationRegressor)
    pl.LightningModule.__init__(module)
    trainer = pl.Trainer(logger=False, enable_progress_bar=False, enable_checkpointing=False)
    trainer.datamodule = NoValidation()  # what on_test_start reads
    with caplog.at_level("WARNING", logger="rotlearn"):
        PostHocCalibration("x", required=False).on_test_start(trainer, module)
    assert "tested uncalibrated" in caplog.text
    with pytest.raises(ConfigError, match="needs a validation set"):
        PostHocCalibration("x", required=True).on_test_start(trainer, module)


def test_records_are_never_written_outside_the_run(make_cfg, tmp_path):
    cfg = make_cfg(RUN)
    model, datamodule, trainer = build(cfg)
    scaling = next(cb for cb in trainer.callbacks if isinstance(cb, PostHocCalibration))
    other = tmp_path / "another_run"
    scaling.dirpath = other  # as if this run's checkpoints lay in another run's directory
    trainer.fit(model, datamodule=datamodule)
    trainer.test(model, datamodule=datamodule, verbose=False)
    assert scaling.record is not None and model.belief_temperature == scaling.record["temperature"]
    assert not (Path(cfg.paths.output_dir) / "checkpoints" / TEMPERATURE_FILE).exists()


def test_an_image_pair_run_calibrates_before_its_ood_evaluation_and_eval_reuses_t(
    make_cfg, tmp_path, monkeypatch
):
    """data=kitti with callbacks=ood: temperature.json and ood_thresholds.json sit side by side
    (the OOD evaluation ran with the temperature set), and rotlearn-eval applies the stored T
    without refitting or writing into the run. With trainer.enable_progress_bar=false neither
    draws a progress bar (a log file got them, a line per batch)."""
    import tqdm.auto

    def no_bar(*args, **kwargs):
        raise AssertionError("a progress bar with trainer.enable_progress_bar=false")

    from hydra import compose, initialize_config_dir

    from rotlearn.checkpoint import THRESHOLDS_FILE
    from rotlearn.cli.evaluate import evaluate
    from rotlearn.paths import config_dir
    from tests.conftest import write_kitti, yaw_sequence

    root = write_kitti(
        tmp_path / "kitti", {"00": yaw_sequence(11, 1.0), "01": yaw_sequence(9, -1.0)}, seed=3
    )
    pairs = [
        "data=kitti", f"data.root={root}", "data.train_sequences=[01]", "data.test_sequences=[00]",
        "data.image_size=16", "data.num_workers=0", "data.eval_batch_size=4",
        "net.channels=[8,8,8,8]", "net.hidden=16", "trainer=cpu", "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
        "callbacks=ood", "callbacks.ood.noise_pairs=4", "callbacks.ood.examples=0",
        "logger=none", "calibrate=true",
    ]  # fmt: skip
    run = tmp_path / "run"
    model, datamodule, trainer = build(make_cfg(pairs, run_dir=run))
    spy = _SeesTheTemperature()
    trainer.callbacks.insert(0, spy)
    with monkeypatch.context() as patch:
        patch.setattr(tqdm.auto, "tqdm", no_bar)
        trainer.fit(model, datamodule=datamodule)
        trainer.test(model, datamodule=datamodule, verbose=False)
    record = read_temperature(run / "checkpoints" / TEMPERATURE_FILE)
    assert record is not None and spy.seen["end"] == record["temperature"]
    assert (run / "checkpoints" / THRESHOLDS_FILE).is_file()
    before = sorted(p.name for p in (run / "checkpoints").iterdir())
    out = tmp_path / "eval"
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("eval", [f"paths.output_dir={out}", f"ckpt={run}"])
    result = evaluate(cfg)
    assert result["temperature"] == record["temperature"]
    assert "calibration/temperature" not in result  # applied, not refitted
    assert "test/tempered_ece" in result  # the level map too
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == before
