"""The measuring pieces of the OOD evaluation on hand-made inputs whose answers are known: AUROC,
precision and the OOD-rejected % at a quantile, the error of the kept pairs, the precision-recall
curve over q, extra (mixed) evaluation sets, the samples file and the example-pair figure; and
one tiny MAV run with extra sets end to end."""

from __future__ import annotations

import math

import pandas as pd
import pytest
import torch

from rotlearn.errors import ConfigError
from rotlearn.ood import (
    OODEvaluation,
    mixed_set,
    precision_recall_curve,
    rejection_row,
    rejection_table,
)
from rotlearn.ood.records import read_samples, write_samples
from rotlearn.report.figures import box_groups, examples_figure
from rotlearn.scores import SCORES, auroc

DT, GAP = SCORES["dt"], SCORES["eigengap"]


def _set(scores, errors, ood, name="dt"):
    return {
        "error": torch.tensor(errors, dtype=torch.float64),
        "corrupted": torch.tensor(ood),
        name: torch.tensor(scores, dtype=torch.float64),
    }


def test_auroc_is_one_when_separated_and_zero_when_reversed_for_both_directions():
    ood = torch.tensor([False, False, True, True])
    low_clean = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert auroc(low_clean, ood, DT.keep_below) == 1.0  # DT: low = confident
    assert auroc(low_clean, ood, GAP.keep_below) == 0.0  # eigen-gap: high = confident
    assert auroc(-low_clean, ood, GAP.keep_below) == 1.0
    assert auroc(-low_clean, ood, DT.keep_below) == 0.0


def test_precision_rejection_and_kept_error_at_a_quantile():
    """Train scores 0..9: q = 0.5 -> threshold 4.5, keep below. Test: 6 clean, 4 OOD."""
    train = torch.arange(10.0)
    scores = torch.tensor([0.0, 1.0, 2.0, 3.0, 8.0, 9.0, 4.0, 6.0, 7.0, 8.0])
    errors = torch.tensor([1.0, 1.0, 1.0, 1.0, 5.0, 5.0, 2.0, 9.0, 9.0, 9.0])
    ood = torch.tensor([False] * 6 + [True] * 4)
    row = rejection_row(DT, 0.5, train, scores, errors, ood)
    # kept: clean 0-3 and OOD sample 6 (score 4 < 4.5)
    assert row["kept_pct"] == pytest.approx(50.0)
    assert row["precision"] == pytest.approx(80.0)  # 4 of 5 kept are clean
    assert row["recall"] == pytest.approx(100.0 * 4 / 6)
    assert row["ood_rejected"] == pytest.approx(75.0)  # 3 of the 4 OOD pairs rejected
    assert row["err_mean_kept"] == pytest.approx((4 * 1.0 + 2.0) / 5)
    assert row["err_median_kept"] == pytest.approx(1.0)
    assert row["err_mean_all"] == pytest.approx(errors.mean().item())


def test_precision_recall_curve_is_rejection_rows_over_q():
    train = torch.arange(100.0)
    test = _set([5.0, 15.0, 50.0, 95.0], [1.0, 1.0, 2.0, 3.0], [False, False, True, True])
    curve = precision_recall_curve(DT, train, test, [0.1, 0.6, 1.0])
    assert [r["q"] for r in curve] == [0.1, 0.6, 1.0]
    assert [r["kept_pct"] for r in curve] == [25.0, 75.0, 100.0]
    assert [r["precision"] for r in curve] == pytest.approx([100.0, 100 * 2 / 3, 50.0])
    assert curve[1] == rejection_row(DT, 0.6, train, test["dt"], test["error"], test["corrupted"])
    assert len(precision_recall_curve(DT, train, test)) == 47  # pr_quantiles: 0.05 .. 0.97


def test_an_extra_set_is_the_test_set_then_its_pairs_as_ood():
    clean = _set([1.0, 2.0], [0.5, 0.5], [False, False])
    extra = _set([7.0, 8.0, 9.0], [3.0, 4.0, 5.0], [False, False, False])
    mixed = mixed_set(clean, extra)
    assert mixed["corrupted"].tolist() == [False, False, True, True, True]
    assert mixed["dt"].tolist() == [1.0, 2.0, 7.0, 8.0, 9.0]
    with pytest.raises(ValueError, match="cannot mix"):
        mixed_set(clean, {"error": extra["error"]})
    sets = {"val": {"dt": torch.arange(10.0)}, "clean": clean, "unseen": mixed}
    frame = rejection_table(sets, [DT], [0.5], {"dt": 0.5})
    assert list(frame["set"]) == ["clean", "unseen"]
    unseen = frame[frame["set"] == "unseen"].iloc[0]
    assert unseen["auroc"] == 1.0 and unseen["precision"] == 100.0
    assert unseen["ood_rejected"] == 100.0 and unseen["err_mean_kept"] == 0.5


def test_samples_file_round_trips_and_feeds_the_box_groups(tmp_path):
    sets = {
        "train": {"error": torch.tensor([1.0, 2.0]), "dt": torch.tensor([-1.0, -2.0])},
        "clean": _set([-1.5, math.nan], [1.0, 2.0], [False, False]),
        "corrupted": _set([-1.5, -0.5], [1.0, 9.0], [False, True]),
        "indoor": _set([-1.5, math.nan, -0.1], [1.0, 2.0, 4.0], [False, False, True]),
        "noise": {"error": torch.tensor([90.0]), "dt": torch.tensor([0.0])},
    }
    back = read_samples(write_samples(tmp_path, sets))
    assert list(back) == list(sets)
    assert "corrupted" not in back["train"] and back["indoor"]["corrupted"].tolist() == [
        False, False, True,
    ]  # fmt: skip
    torch.testing.assert_close(back["indoor"]["dt"], sets["indoor"]["dt"].double(), equal_nan=True)
    groups = box_groups(DT.name, back)
    assert list(groups) == ["train", "test", "erased", "indoor", "noise"]
    assert groups["test"].tolist() == [-1.5]  # NaN dropped
    assert groups["erased"].tolist() == [-0.5] and groups["indoor"].tolist() == [-0.1]
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"bad\.csv: not an OOD samples file"):
        read_samples(tmp_path / "bad.csv")


def test_the_example_figure_has_one_row_of_two_frames_per_pair():
    images = torch.randint(0, 256, (3, 6, 8, 8), dtype=torch.uint8)
    captions = [{"erased": i > 0, "error": 1.5 * i, "dt": -2.0 + i} for i in range(3)]
    fig = examples_figure(images, captions)
    axes = fig.get_axes()
    assert len(axes) == 6
    assert axes[0].get_title(loc="left").startswith("clean, err 0.00 deg: DT -2")
    assert axes[2].get_title(loc="left").startswith("erased, err 1.50 deg")
    assert axes[1].images[0].get_array().shape == (8, 8, 3)
    gray = examples_figure(images[:, :2], captions[:1] * 3)
    assert gray.get_axes()[0].images[0].get_array().shape == (8, 8)


def test_extra_sets_are_checked_when_the_callback_is_built():
    OODEvaluation(extra_sets={"indoor": {"test_scenes": ["indoor"]}})
    with pytest.raises(ConfigError, match=r"extra_sets\.clean"):
        OODEvaluation(extra_sets={"clean": {"test_scenes": ["indoor"]}})
    with pytest.raises(ConfigError, match=r"extra_sets\.indoor"):
        OODEvaluation(extra_sets={"indoor": {}})
    for key in ("root", "cache_dir"):  # a received run's extra set wrote a cache anywhere
        with pytest.raises(ConfigError, match=rf"extra_sets\.other\.{key}.*names no files"):
            OODEvaluation(extra_sets={"other": {"test_scenes": ["indoor"], key: "/elsewhere"}})


def test_a_tiny_mav_run_scores_its_extra_sets(tmp_path, make_cfg):
    """Train on outdoor, test on outdoor; the extra set adds the indoor test pairs as OOD."""
    from rotlearn.cli.train import train
    from tests.conftest import write_mav
    from tests.ood.test_ood import tiny_mav_overrides

    run_dir = tmp_path / "run"
    overrides = [
        *tiny_mav_overrides(write_mav(tmp_path / "mav", frames=30)),
        "trainer.max_epochs=1",
        "callbacks.ood.extra_sets={indoor: {test_scenes: [indoor]}}",
        "callbacks.ood.examples=2",
    ]
    train(make_cfg(overrides, run_dir=run_dir))
    frame = pd.read_csv(run_dir / "ood.csv")
    assert set(frame["set"]) == {"clean", "corrupted", "indoor"}
    clean, indoor = (frame[frame["set"] == s].iloc[0] for s in ("clean", "indoor"))
    # indoor: 9 pairs, round(0.3 * 9) = 3 of them test pairs, appended as OOD
    assert indoor["n"] == clean["n"] + 3 and indoor["n_corrupted"] == 3
    sets = read_samples(run_dir / "ood_samples.csv")
    assert {"val", "clean", "corrupted", "noise", "indoor"} == set(sets)
    assert (run_dir / "ood_examples.png").stat().st_size > 0
    bad = [o for o in overrides if "extra_sets" not in o]
    bad.append("callbacks.ood.extra_sets={x: {nope: 1}}")
    with pytest.raises(ConfigError, match=r"extra_sets\.x\.nope"):  # at setup, before training
        train(make_cfg(bad, run_dir=tmp_path / "r2"))
    assert not (tmp_path / "r2" / "checkpoints").exists()


def test_the_reproduction_configs_compose_and_validate(make_cfg, on_disk):
    """`make reproduce-ood`'s three training commands: Table I with the paper's rows, the A head
    with the Bingham loss, and Fig. 8 with its extra sets."""
    from rotlearn.config import validate

    kitti = make_cfg(["experiment=kitti_ood_demo"])
    validate(on_disk(kitti))
    rows = kitti.report.paper.rows
    assert [(r.rep, r.get("score")) for r in rows] == [
        ("quat", None), ("sixd", None), ("sixd", "autoencoder"), ("a", None), ("a", "dt"),
    ]  # fmt: skip
    assert rows[4].precision == 99.0 and kitti.callbacks.ood.table.dt == 0.75
    assert kitti.callbacks.ood.autoencoder_ckpt is None  # its own run: kitti_autoencoder_demo
    for data in ("kitti", "mav"):
        ae = make_cfg([f"experiment={data}_autoencoder_demo"])
        ood = make_cfg([f"experiment={data}_ood_demo"])
        assert ae.model._target_.endswith("AutoEncoderModule")
        assert ae.data.image_size == ood.data.image_size and ae.data.mean == ood.data.mean
        # the same split: the AE's thresholds come from validation pairs it never trained on
        split = ("train_sequences", "test_sequences", "val_sequences", "val_fraction",
                 "test_scenes")  # fmt: skip
        assert [ae.data.get(k) for k in split] == [ood.data.get(k) for k in split]
    bingham = make_cfg(["experiment=kitti_ood_demo", "rep=a", "loss=bingham"])
    validate(on_disk(bingham))
    assert bingham.loss._target_.endswith("BinghamNLLLoss")
    mav = make_cfg(["experiment=mav_ood_demo"])
    validate(on_disk(mav))
    assert dict(mav.callbacks.ood.extra_sets) == {
        "indoor": {"test_scenes": ["indoor"]},
        "indoor_transition": {"test_scenes": ["indoor", "transition"]},
    }
    assert set(mav.report.ood.sets) == {"clean", "indoor", "indoor_transition"}
    assert make_cfg(["data=kitti", "callbacks=ood"]).callbacks.ood.extra_sets is None
