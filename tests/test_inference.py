"""Safe checkpoint loading, the Predictor API and rotlearn-predict."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import rotlearn
from rotlearn.checkpoint import UnsafeCheckpointError, load_checkpoint
from rotlearn.cli.predict import main as predict_main
from rotlearn.cli.predict import read_point_pairs
from rotlearn.cli.train import build, train
from rotlearn.errors import InputAdjustedWarning
from rotlearn.geometry import quat_to_rotmat, so3_exp
from tests.conftest import SMALL_NET, point_pairs

FAST = ["data=tiny", "trainer=cpu", "trainer.enable_progress_bar=false", *SMALL_NET]


@pytest.fixture(scope="module")
def trained_runs(tmp_path_factory) -> dict[str, Path]:
    """One finished tiny run per head kind (with and without a Bingham belief)."""
    from hydra import compose, initialize_config_dir

    from rotlearn.paths import config_dir

    runs = {}
    for rep in ("a", "sixd"):
        out = tmp_path_factory.mktemp(rep)
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose("train", [f"paths.output_dir={out}", f"rep={rep}", *FAST,
                                    "trainer.max_epochs=1", "logger=none",
                                    "calibrate=false"])  # fmt: skip
        train(cfg)
        runs[rep] = out
    return runs


def test_a_run_trained_with_a_usual_lightning_callback_loads(make_cfg, tmp_path):
    """A run's saved config names every callback it trained with; weight averaging (tried for
    issue 25 from the command line) is one of Lightning's usual ones, so its run loads instead of
    being refused as untrusted."""
    out = tmp_path / "swa"
    swa = "+callbacks.swa._target_=lightning.pytorch.callbacks.StochasticWeightAveraging"
    cfg = make_cfg([*FAST, "rep=a", "trainer.max_epochs=2", "logger=none", "calibrate=false",
                    swa, "+callbacks.swa.swa_lrs=0.001", "+callbacks.swa.swa_epoch_start=1"],
                   run_dir=out)  # fmt: skip
    train(cfg)
    estimate = rotlearn.load(out)(point_pairs())
    assert estimate.R.shape == (3, 3, 3)


def test_predictor_reproduces_the_trained_model(trained_runs, make_cfg):
    run = trained_runs["a"]
    predictor = rotlearn.load(run)  # a run directory: the weights its test scored (last.ckpt)
    cfg = make_cfg(["rep=a", *FAST])
    model, _, _ = build(cfg)
    model.load_state_dict(load_checkpoint(run)["state_dict"])
    model.eval()
    x = point_pairs()
    with torch.no_grad():
        expected = model(x)
    estimate = predictor(x)
    assert torch.allclose(estimate.R, expected.R, atol=1e-6)
    assert torch.allclose(quat_to_rotmat(estimate.q), estimate.R, atol=1e-5)
    assert (estimate.q[:, 3] >= 0).all()
    assert (estimate.dispersion <= 0).all() and torch.allclose(
        estimate.dt, estimate.dispersion.sum(-1)
    )
    assert estimate.keep is None  # this checkpoint carries no calibrated OOD threshold


def test_heads_without_a_belief_give_no_dispersion(trained_runs):
    estimate = rotlearn.load(trained_runs["sixd"] / "checkpoints" / "best.ckpt")(point_pairs())
    assert estimate.R.shape == (3, 3, 3) and estimate.dispersion is None and estimate.dt is None


def test_a_single_input_is_a_batch_of_one(trained_runs):
    estimate = rotlearn.load(trained_runs["a"])(point_pairs(1)[0].numpy())
    assert estimate.R.shape == (1, 3, 3)


class _Payload:
    """Unpickling this runs code: it creates the file named in `marker`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_checkpoint_carrying_code_is_refused_and_not_run(trained_runs, tmp_path):
    marker = tmp_path / "pwned"
    checkpoint = load_checkpoint(trained_runs["a"])
    checkpoint["extra"] = _Payload(marker)
    evil = tmp_path / "evil.ckpt"
    torch.save(checkpoint, evil)
    with pytest.raises(UnsafeCheckpointError, match=r"refusing to load .*evil\.ckpt"):
        rotlearn.load(evil)
    assert not marker.exists()
    torch.load(evil, weights_only=False)  # the payload is real: a full unpickler runs it
    assert marker.exists()


def test_missing_or_foreign_checkpoints_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        rotlearn.load(tmp_path / "nothing.ckpt")
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"state_dict": {}}, foreign)
    with pytest.raises(ValueError, match="not a rotlearn checkpoint"):
        rotlearn.load(foreign)


BAD_INPUTS = {
    "NaN": lambda: point_pairs().index_put_(
        (torch.tensor([1]), torch.tensor([2])), torch.tensor(np.nan)
    ),
    "Inf": lambda: point_pairs().index_put_(
        (torch.tensor([0]), torch.tensor([0])), torch.tensor(np.inf)
    ),
    "too few dims": lambda: torch.randn(6),
    "wrong width": lambda: torch.randn(2, 16, 5),
    "no points": lambda: torch.randn(2, 0, 6),
    "no samples": lambda: torch.randn(0, 16, 6),
    "integers": lambda: torch.ones(2, 16, 6, dtype=torch.int64),
    "booleans": lambda: torch.ones(2, 16, 6, dtype=torch.bool),
    "complex": lambda: torch.randn(2, 16, 6, dtype=torch.complex64),
    "numpy ints": lambda: np.ones((2, 16, 6), dtype=np.int32),
    "a list": lambda: [[0.0] * 6] * 16,
    "a string": lambda: "points.txt",
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_inputs_are_refused_with_a_reason(trained_runs, case):
    predictor = rotlearn.load(trained_runs["a"])
    with pytest.raises((TypeError, ValueError)) as err:
        predictor(BAD_INPUTS[case]())
    assert len(str(err.value)) > 20


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    shape=st.lists(st.integers(0, 7), min_size=0, max_size=4),
    dtype=st.sampled_from([torch.float16, torch.float32, torch.float64, torch.int32, torch.uint8]),
    poison=st.sampled_from([None, np.nan, np.inf, -np.inf, 1e30]),
)
@pytest.mark.filterwarnings("ignore::rotlearn.errors.InputAdjustedWarning")  # Gaussian u_i
def test_fuzzed_inputs_give_rotations_or_a_clear_refusal(trained_runs, shape, dtype, poison):
    predictor = rotlearn.load(trained_runs["a"])
    x = torch.randn(*shape).to(dtype) if shape else torch.randn(()).to(dtype)
    if poison is not None and x.numel() and x.is_floating_point():
        x.view(-1)[0] = poison
    try:
        estimate = predictor(x)
    except (TypeError, ValueError, FloatingPointError) as exc:
        assert str(exc)
        return
    assert torch.isfinite(estimate.R).all() and torch.isfinite(estimate.q).all()
    det = torch.linalg.det(estimate.R.double())
    assert torch.allclose(det, torch.ones_like(det), atol=1e-4)


def test_predict_command_reads_text_and_npy_pairs(trained_runs, tmp_path, capsys):
    points = point_pairs(1)[0].numpy()
    text = tmp_path / "pairs.txt"
    text.write_text("# ux uy uz vx vy vz\n" + "\n".join(" ".join(map(str, r)) for r in points))
    npy = tmp_path / "pairs.npy"
    np.save(npy, points)
    assert np.allclose(read_point_pairs(text), read_point_pairs(npy), atol=1e-6)
    assert predict_main([str(trained_runs["a"]), str(text), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert len(result["q_xyzw"]) == 4 and result["dt_score"] <= 0 and len(result["dispersion"]) == 3
    assert 0 < result["uncertainty_deg"] <= 180 and result["uncertainty_level"] == 0.9
    assert result["angle_deg"] == pytest.approx(
        math.degrees(2 * math.atan2(np.linalg.norm(result["q_xyzw"][:3]), result["q_xyzw"][3]))
    )
    assert predict_main([str(trained_runs["a"]), str(npy)]) == 0
    text = capsys.readouterr().out
    assert f"  rotation     {result['angle_deg']:.3f} deg about (" in text
    assert f"  uncertainty  {result['uncertainty_deg']:.3g} deg: 90 % of the belief" in text
    assert "  OOD check    no threshold with this checkpoint" in text  # none calibrated here
    assert predict_main([str(trained_runs["sixd"]), str(npy)]) == 0
    assert "uncertainty  none: rep=sixd defines no belief" in capsys.readouterr().out
    np.save(npy, np.stack([points, points]))  # (B, N, 6): each input is a set of N pairs
    assert predict_main([str(trained_runs["sixd"]), str(npy)]) == 0
    text = capsys.readouterr().out
    assert text.startswith("input 0:\n") and "\ninput 1:\n" in text  # "pair 0:" it said


def test_predict_command_names_the_bad_line(trained_runs, tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("0 0 1 0 0 1\n0 1 0 0 1\n")
    assert predict_main([str(trained_runs["a"]), str(bad)]) == 2
    assert f"{bad}:2: expected 6 numbers" in capsys.readouterr().err
    bad.write_text("0 0 1 0 0 one\n")
    assert predict_main([str(trained_runs["a"]), str(bad)]) == 2
    assert f"{bad}:1: not a number" in capsys.readouterr().err
    assert predict_main([str(trained_runs["a"]), os.fspath(tmp_path / "absent.txt")]) == 2


def test_predict_command_says_what_a_point_model_reads(trained_runs, tmp_path, capsys):
    image = tmp_path / "000000.png"
    image.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    objects = tmp_path / "objects.npy"
    np.save(objects, np.array([[None] * 6], dtype=object), allow_pickle=True)
    cases = {
        image: f"{image}:1: not UTF-8 text (byte 0); a point model reads a .npy array (N, 6) or "
        "(B, N, 6) or text rows 'ux uy uz vx vy vz'",
        objects: f"{objects}: holds Python objects, which rotlearn never unpickles",
        tmp_path: f"{tmp_path}: a folder; a point model reads one point-pair file",
    }
    for path, message in cases.items():
        assert predict_main([str(trained_runs["a"]), str(path)]) == 2
        err = capsys.readouterr().err
        assert err == f"rotlearn-predict: {message}\n" and "allow_pickle" not in err


def test_large_batches_run_in_chunks_of_bounded_size(trained_runs):
    """Memory is bounded for any batch: the network sees chunks of at most chunk_elements input
    numbers, and the result equals one pass over the whole batch."""
    whole = rotlearn.load(trained_runs["a"], chunk_elements=10**9)
    chunked = rotlearn.load(trained_runs["a"], chunk_elements=16 * 6 * 7)
    seen: list[int] = []
    chunked.net.register_forward_hook(lambda module, args, out: seen.append(args[0].shape[0]))
    points = point_pairs(n=50)
    reference, estimate = whole(points), chunked(points)
    assert seen == [7] * 7 + [1]
    for key in ("R", "q", "dispersion", "dt"):
        torch.testing.assert_close(getattr(estimate, key), getattr(reference, key))
    assert estimate.R.shape == (50, 3, 3)
    with pytest.raises(ValueError, match="chunk_elements"):
        rotlearn.load(trained_runs["a"], chunk_elements=0)


def test_a_cloud_over_one_chunk_is_refused_before_the_network(trained_runs, tmp_path, capsys):
    """One sample cannot be split: a .npy of 5 million point pairs (120 MB, under the file cap)
    ran PointNet's 1024-channel layer on all of them (about 20 GB), an allocation traceback
    under a memory limit. A sample over chunk_elements numbers is refused in one line."""
    predictor = rotlearn.load(trained_runs["a"], chunk_elements=16 * 6)
    predictor.net.register_forward_hook(lambda *args: pytest.fail("the network ran"))
    said = r"^a sample of 17 points \(102 numbers\) is over the 96 numbers a forward pass takes"
    with pytest.raises(ValueError, match=said + r" \(chunk_elements\): subsample it"):
        predictor(point_pairs(2, 0).repeat(1, 2, 1)[:, :17])
    path = tmp_path / "big.npy"
    np.save(path, np.tile(point_pairs(1)[0].numpy(), (2**20 // 16 // 6 + 1, 1)))  # 1 point over
    assert predict_main([str(trained_runs["a"]), str(path)]) == 2
    assert capsys.readouterr().err.startswith("rotlearn-predict: a sample of 174768 points")


def test_thresholds_beside_the_checkpoint_give_keep_flags(trained_runs, tmp_path):
    import shutil

    from rotlearn.checkpoint import THRESHOLDS_FILE
    from rotlearn.ood.records import write_thresholds

    run = tmp_path / "run"
    shutil.copytree(trained_runs["a"], run)
    ckpt = run / "checkpoints" / "last.ckpt"
    before = ckpt.read_bytes()
    write_thresholds(run / "checkpoints", {"score": "dt", "threshold": -5.0, "q": 0.75})
    assert ckpt.read_bytes() == before  # the checkpoint itself is never rewritten
    predictor = rotlearn.load(run)  # a file written before the reference set was recorded
    assert predictor.ood == {"score": "dt", "threshold": -5.0, "q": 0.75}
    estimate = predictor(point_pairs())
    assert torch.equal(estimate.keep, estimate.dt < -5.0)
    write_thresholds(run / "checkpoints", {"score": "dt", "threshold": -5.0, "q": 0.75,
                                           "reference": "train"})  # fmt: skip
    assert rotlearn.load(run).ood["reference"] == "train"

    path = run / "checkpoints" / THRESHOLDS_FILE
    for text, reason in [
        ("not json", "not a JSON OOD threshold file"),
        ('{"score": "dt", "threshold": NaN, "q": 0.5}', "NaN is not a number"),
        ('{"score": "dt", "threshold": "1", "q": 0.5}', "threshold must be a finite number"),
        ('{"score": "dt", "threshold": true, "q": 0.5}', "threshold must be a finite number"),
        ('{"score": "dt", "threshold": 1.0, "q": 2}', r"q must lie in \[0, 1\]"),
        ('{"score": "dt", "threshold": -1e300, "q": 0.5}', "within float32's range"),
        ('{"score": "dt", "threshold": 1.0}', r"must be \{score: str, threshold: number"),
        ('{"score": "dt", "threshold": 1.0, "q": 0.5, "x": 1}', r"got \['q', 'score'"),
        ('{"score": "dt", "threshold": 1.0, "q": 0.5, "reference": "test"}', "reference must be"),
        ('{"score": "dt", "threshold": 1.0, "q": 0.5, "reference": []}', "reference must be"),
        ('["dt", 1.0, 0.5]', "got list"),
    ]:
        path.write_text(text)
        with pytest.raises(ValueError, match=reason) as info:
            rotlearn.load(run)
        assert str(path) in str(info.value)
    for text, reason in [  # hostile numbers and shapes (the temperature file's tests share them)
        ('{"score": "dt", "threshold": 1' + "0" * 400 + ', "q": 0.5}', "threshold must be a"),
        ("[" * 2000 + "]" * 2000, "nested too deeply"),
        (" " * 5000, "too large"),
    ]:
        path.write_text(text)
        with pytest.raises(ValueError, match=reason) as info:
            rotlearn.load(run)
        assert str(path) in str(info.value)


# -- the calibrated temperature (calibrate=true: checkpoints/temperature.json) -------------------


def _temperature_record(t: float = 2.5, checkpoint: str = "last.ckpt") -> dict:
    return {"temperature": t, "checkpoint": checkpoint, "val_nll": -1.5,
            "val_nll_uncalibrated": -1.0, "num_val": 16}  # fmt: skip


@pytest.fixture
def calibrated_run(trained_runs, tmp_path) -> Path:
    """A copy of the A head's run with a temperature record for its last.ckpt (T = 2.5)."""
    import shutil

    from rotlearn.checkpoint import TEMPERATURE_FILE

    run = tmp_path / "run"
    shutil.copytree(trained_runs["a"], run)
    (run / "checkpoints" / TEMPERATURE_FILE).write_text(json.dumps(_temperature_record()))
    return run


def test_load_applies_the_checkpoints_temperature_to_the_belief(trained_runs, calibrated_run):
    x = point_pairs(4)
    plain = rotlearn.load(trained_runs["a"])(x)
    predictor = rotlearn.load(calibrated_run)
    assert predictor.temperature == 2.5
    tempered = predictor(x)
    assert plain.temperature == 1.0 and tempered.temperature == 2.5
    torch.testing.assert_close(tempered.R, plain.R)  # the mode is untouched
    torch.testing.assert_close(tempered.A, plain.A / 2.5)
    torch.testing.assert_close(tempered.dt, plain.dt / 2.5)
    torch.testing.assert_close(tempered.dispersion, plain.dispersion / 2.5)
    assert tempered.A.shape == (4, 4, 4) and tempered.F is None  # the A head has no F
    # the keep flags compare the tempered DT with the threshold (written after calibration)
    from rotlearn.ood.records import write_thresholds

    threshold = float(tempered.dt.median())
    write_thresholds(calibrated_run / "checkpoints", {"score": "dt", "threshold": threshold,
                                                      "q": 0.5})  # fmt: skip
    assert torch.equal(rotlearn.load(calibrated_run)(x).keep, tempered.dt < threshold)
    # the best checkpoint was not calibrated: loading it leaves the belief as trained
    best = rotlearn.load(calibrated_run / "checkpoints" / "best.ckpt")
    assert best.temperature == 1.0


def test_a_temperature_fitted_for_another_checkpoint_is_ignored_with_a_warning(
    calibrated_run, caplog
):
    from rotlearn.checkpoint import TEMPERATURE_FILE

    path = calibrated_run / "checkpoints" / TEMPERATURE_FILE
    path.write_text(json.dumps(_temperature_record(checkpoint="best.ckpt")))
    with caplog.at_level("WARNING", logger="rotlearn"):
        predictor = rotlearn.load(calibrated_run)  # last.ckpt
    assert predictor.temperature == 1.0
    assert "fitted for best.ckpt, not last.ckpt" in caplog.text and str(path) in caplog.text
    assert rotlearn.load(calibrated_run / "checkpoints" / "best.ckpt").temperature == 2.5


def test_estimates_sample_and_score_their_belief(calibrated_run, trained_runs):
    from rotlearn import bingham

    estimate = rotlearn.load(calibrated_run)(point_pairs(3))
    draws = estimate.sample(50, generator=torch.Generator().manual_seed(0))
    assert draws.shape == (3, 50, 4)
    torch.testing.assert_close(draws.norm(dim=-1), torch.ones(3, 50))
    scores = estimate.log_prob(draws)
    assert scores.shape == (3, 50)
    torch.testing.assert_close(scores[1], bingham.log_prob(estimate.A[1], draws[1]))
    one = estimate.log_prob(estimate.q)
    assert one.shape == (3,)
    torch.testing.assert_close(estimate.log_prob(estimate.R), one, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(
        estimate.log_prob(quat_to_rotmat(draws)), scores, rtol=1e-4, atol=1e-4
    )
    assert (one >= scores.max(-1).values - 1e-5).all()  # the mode is the most likely rotation
    with pytest.raises(ValueError, match=r"quaternions \(B, 4\) or \(B, n, 4\)"):
        estimate.log_prob(torch.zeros(3, 5))
    with pytest.raises(ValueError, match="2 entries for 3 estimates"):
        estimate.log_prob(estimate.q[:2])
    no_belief = rotlearn.load(trained_runs["sixd"])(point_pairs(2))
    assert no_belief.A is None and no_belief.F is None
    with pytest.raises(ValueError, match="defines no belief"):
        no_belief.sample(3)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("not json", "not a JSON temperature file"),
        ("", "not a JSON temperature file"),
        ('{"temperature": NaN}', "NaN is not a number"),
        ('{"temperature": Infinity}', "Infinity is not a number"),
        (json.dumps(_temperature_record(-2.0)), "temperature must be a number in"),
        (json.dumps(_temperature_record(0.0)), "temperature must be a number in"),
        (json.dumps(_temperature_record(1e-320)), "temperature must be a number in"),
        (json.dumps(_temperature_record(1e-300)), "A / T must stay finite"),  # 1 / T is finite
        (json.dumps(_temperature_record(1e-36)), "A / T must stay finite"),  # A / T is not
        (json.dumps(_temperature_record(1e300)), "A / T must stay finite"),
        (json.dumps(_temperature_record(True)), "temperature must be a number in"),
        (json.dumps(_temperature_record("2.5")), "temperature must be a number in"),
        (json.dumps(_temperature_record()).replace("2.5", "1e999"), "must be a number in"),
        (json.dumps(_temperature_record()).replace("2.5", "1" + "0" * 400), "must be a number in"),
        (json.dumps(_temperature_record(checkpoint="../other/last.ckpt")), "file name"),
        (json.dumps(_temperature_record(checkpoint="")), "file name"),
        (json.dumps(_temperature_record(checkpoint=7)), "file name"),
        (json.dumps({**_temperature_record(), "num_val": 0}), "num_val must be a positive"),
        (json.dumps({**_temperature_record(), "num_val": 1.5}), "num_val must be a positive"),
        (json.dumps({**_temperature_record(), "val_nll": None}), "val_nll must be a finite"),
        (json.dumps({**_temperature_record(), "extra": 1}), r"must be \{temperature.*'extra'"),
        (json.dumps({"temperature": 2.0}), r"got \['temperature'\]"),
        (json.dumps([2.5, "last.ckpt"]), "got list"),
        ("[" * 2000 + "]" * 2000, "nested too deeply"),
        (" " * 4000 + json.dumps(_temperature_record()), "too large"),
        ("\udcff", "not a JSON temperature file"),
    ],
)
def test_a_hostile_temperature_file_is_refused_naming_it(calibrated_run, text, reason):
    from rotlearn.checkpoint import TEMPERATURE_FILE, read_temperature

    path = calibrated_run / "checkpoints" / TEMPERATURE_FILE
    path.write_bytes(text.encode("utf-8", "surrogateescape"))
    for load in (lambda: rotlearn.load(calibrated_run), lambda: read_temperature(path)):
        with pytest.raises(ValueError, match=reason) as info:
            load()
        assert str(path) in str(info.value)


def test_a_genuine_temperature_record_reads_back_whole(calibrated_run):
    from rotlearn.checkpoint import TEMPERATURE_FILE, load_run, read_temperature

    path = calibrated_run / "checkpoints" / TEMPERATURE_FILE
    assert read_temperature(path) == {**_temperature_record(), "credible_masses": None}
    path.write_text(json.dumps({**_temperature_record(), "val_nll_uncalibrated": None}))
    assert read_temperature(path)["val_nll_uncalibrated"] is None
    assert load_run(calibrated_run).temperature == 2.5
    path.unlink()
    assert read_temperature(path) is None and load_run(calibrated_run).temperature == 1.0


def test_predictor_refuses_a_bad_temperature(trained_runs):
    predictor = rotlearn.load(trained_runs["a"])
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="temperature must be a finite number > 0"):
            rotlearn.inference.Predictor(predictor.net, predictor.head, temperature=bad)


def test_predict_command_reports_the_temperature(calibrated_run, tmp_path, capsys):
    path = tmp_path / "pairs.npy"
    np.save(path, point_pairs(1)[0].numpy())
    assert predict_main([str(calibrated_run), str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["temperature"] == 2.5
    assert predict_main([str(calibrated_run), str(path)]) == 0
    assert "temperature 2.5" in capsys.readouterr().out


def test_load_of_several_runs_is_their_ensemble_and_calibrates_on_held_out_data(
    trained_runs, tmp_path, monkeypatch
):
    """rotlearn.load([run, its copy]): the product of two identical beliefs (A doubled, the
    same rotation, no disagreement); Predictor.calibrate fits its temperature and level map. The
    same run listed twice is refused (its belief would count twice)."""
    x = point_pairs(64)
    single = rotlearn.load(trained_runs["a"])(x)
    for twice in ([trained_runs["a"]] * 2, [trained_runs["a"], trained_runs["a"] / "checkpoints"
                                              / "last.ckpt"]):  # fmt: skip
        with pytest.raises(ValueError, match=r"is .* again \(.*\): each member of an"):
            rotlearn.load(twice)
    spelled = [trained_runs["a"], trained_runs["a"] / ".." / trained_runs["a"].name]
    with monkeypatch.context() as patch:  # refused before any member is loaded (50 copies: 5.6 GB)
        patch.setattr(rotlearn.inference, "load_run", lambda *a, **k: pytest.fail("loaded"))
        with pytest.raises(ValueError, match=r"is .* again \(.*\): each member of an"):
            rotlearn.load(spelled)
    copy = shutil.copytree(trained_runs["a"], tmp_path / "copy")
    ensemble = rotlearn.load([trained_runs["a"], copy])
    estimate = ensemble(x)
    torch.testing.assert_close(estimate.A, 2 * single.A)
    torch.testing.assert_close(estimate.R, single.R)
    assert estimate.disagreement.shape == (64,) and float(estimate.disagreement.max()) < 1e-2
    assert single.disagreement is None
    # held-out data: the truth is the single model's rotation, jittered
    jitter = 0.05 * torch.randn(64, 3, generator=torch.Generator().manual_seed(0))
    targets = single.R @ so3_exp(jitter)
    fit = ensemble.calibrate(x, targets)
    assert fit["nll_after"] <= fit["nll_before"] + 1e-9
    assert ensemble.temperature == fit["temperature"] and ensemble.level_map is not None
    calibrated = ensemble(x)
    torch.testing.assert_close(calibrated.A, estimate.A / fit["temperature"])
    assert 0.0 <= float(calibrated.credible_mass(0.9)) <= 1.0
    with pytest.raises(ValueError, match="no belief"):
        rotlearn.load([trained_runs["a"], trained_runs["sixd"]])


def test_calibrate_takes_one_rotation_per_input_and_needs_a_belief(trained_runs):
    """Predictor.calibrate: numpy targets as numpy inputs are taken; a count of targets that is
    not the inputs' is refused (one target was broadcast over five inputs and fitted, T = 2.7e6);
    a head without a belief is named (it was "'NoneType' object has no attribute 'double'")."""
    x = point_pairs(5)
    predictor = rotlearn.load(trained_runs["a"])
    targets = predictor(x).R
    fit = predictor.calibrate(x.numpy(), targets.numpy())
    assert fit["num"] == 5 and math.isfinite(fit["temperature"])
    for wrong in (targets[:1], targets[:3], targets[..., :2]):
        with pytest.raises(ValueError, match=r"^targets must be \(5, 3, 3\) rotations or \(5, 4\)"):
            predictor.calibrate(x, wrong)
    with pytest.raises(ValueError, match="this model's head defines no belief"):
        rotlearn.load(trained_runs["sixd"]).calibrate(x, targets)


NO_CUDA = r"device cuda:99: this machine has (no CUDA device|\d+ CUDA device)"


@pytest.mark.parametrize(
    ("device", "message"), [("bogus", r"device bogus: not a device name"), ("cuda:99", NO_CUDA)]
)
def test_predict_refuses_a_device_it_cannot_use_in_one_line(
    calibrated_run, tmp_path, capsys, device, message
):
    path = tmp_path / "pairs.npy"
    np.save(path, point_pairs(1)[0].numpy())
    assert predict_main([str(calibrated_run), str(path), "--device", device]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.count("\n") == 1


@pytest.mark.parametrize(
    ("args", "error", "message"),
    [
        (("cuda:99",), ValueError, NO_CUDA),  # was torch's AssertionError on a CPU-only torch
        (("bogus",), ValueError, r"device bogus: not a device name"),
    ],
)
def test_load_names_a_device_it_cannot_use(trained_runs, args, error, message):
    with pytest.raises(error, match=message):
        rotlearn.load(trained_runs["a"], *args)


@pytest.mark.parametrize("what", [123, None, [Path("run"), 3]])
def test_load_names_what_it_takes(what):
    with pytest.raises(TypeError, match=r"expected a run directory or \.ckpt path, or a list"):
        rotlearn.load(what)


def test_predict_notes_only_the_changes_it_made_to_the_input(
    trained_runs, tmp_path, capsys, monkeypatch
):
    """`rotlearn-predict` words rotlearn's `InputAdjustedWarning` as a note on the input file;
    any other warning raised while predicting (a library's) stays a warning of its own."""
    from rotlearn.data.synthetic import SyntheticWahbaDataModule

    prepare = SyntheticWahbaDataModule.prepare_points

    def advising(points):
        warnings.warn("a library's advice", UserWarning, stacklevel=1)
        return prepare(points)

    monkeypatch.setattr(SyntheticWahbaDataModule, "prepare_points", staticmethod(advising))
    npy = tmp_path / "pairs.npy"
    np.save(npy, point_pairs(1)[0].numpy())
    with pytest.warns(UserWarning, match="a library's advice"):
        assert predict_main([str(trained_runs["a"]), str(npy)]) == 0
    assert "note:" not in capsys.readouterr().err


def test_predict_answers_inputs_the_net_overflows_on_in_one_line(calibrated_run, tmp_path, capsys):
    path = tmp_path / "huge.npy"
    huge = np.full((1, 8, 6), 1e300)
    huge[..., :3] = [1.0, 0.0, 0.0]  # unit u_i (longer ones are divided by their length)
    np.save(path, huge)
    assert predict_main([str(calibrated_run), str(path)]) == 2
    assert capsys.readouterr().err == (
        "rotlearn-predict: the network output is not finite for these inputs\n"
    )


def test_point_pairs_are_read_as_the_synthetic_training_pairs_with_unit_u(
    trained_runs, tmp_path, capsys
):
    """The training u_i are unit vectors: a network given longer ones (the quickstart's example
    once drew them from a normal distribution) answered 25 deg off with a belief sure to 1 deg.
    Each pair is divided by |u_i| (v_i = R u_i + noise keeps its relation), with a note."""
    unit = point_pairs(2)
    longer = unit * torch.linspace(0.25, 4.0, 16).unsqueeze(-1)  # each pair scaled alike
    predictor = rotlearn.load(trained_runs["a"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        expected = predictor(unit)  # unit u_i: no note
    with pytest.warns(InputAdjustedWarning, match=r"^30 of 32 u_i were not of unit length; each"):
        scaled = predictor(longer)  # one of the 16 lengths per input is 1
    assert torch.allclose(scaled.q, expected.q, atol=1e-5)
    assert torch.allclose(scaled.A, expected.A, rtol=1e-4, atol=1e-3)
    zero = unit.clone()
    zero[1, 5, :3] = 0
    with pytest.raises(ValueError, match=r"^pair 5 of input 1: u_i = 0 has no direction"):
        predictor(zero)
    npy = tmp_path / "pairs.npy"
    np.save(npy, longer[0].numpy())
    assert predict_main([str(trained_runs["a"]), str(npy), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["q_xyzw"] == pytest.approx(expected.q[0].tolist(), abs=1e-5)
    assert captured.err == (f"rotlearn-predict: note: {npy}: 15 of 16 u_i were not of unit length;"
                            " each pair (u_i, v_i) was divided by |u_i|, as the network was trained"
                            " on unit u_i\n")  # fmt: skip


def test_predict_names_a_data_config_that_does_not_build_even_without_words(monkeypatch):
    """A datamodule that raised an error without a message made rotlearn-predict's one-line
    refusal an IndexError traceback: the error's type stands in for the words."""
    from types import SimpleNamespace

    import hydra.utils
    from hydra.errors import InstantiationException

    from rotlearn.cli.predict import _read_input

    def refuse(config):
        raise InstantiationException("") from ValueError()

    monkeypatch.setattr(hydra.utils, "instantiate", refuse)
    predictor = SimpleNamespace(image_size=16, config={"data": {}})
    with pytest.raises(ValueError, match=r"^run: its data config does not build: ValueError$"):
        _read_input(predictor, ["a.png", "b.png"], "run")
