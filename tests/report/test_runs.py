"""Runs grouped into settings (rotlearn.report.runs): every key that differs, never what was swept
pooled; the trial keys a sweep declares pooled; --group-by and --pool."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from rotlearn.report import collect_runs, make_report


def _run(run: Path, config: dict, choices: dict, overrides: list[str], error: float) -> None:
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    hydra = {"hydra": {"runtime": {"choices": choices}}}
    (run / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(hydra))
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    metrics = {"test/err_mean": error, "test/err_median": error}
    (run / "metrics.json").write_text(json.dumps(metrics))
    (run / "status.json").write_text(json.dumps({"status": "COMPLETED"}))


def _grid(sweep: Path, report: dict | None = None, hidden: bool = False) -> None:
    """rep x optim.lr x seed, 8 runs; the error grows with the lr index and the head."""
    num = 0
    for rep in ("a", "sixd"):
        for lr in (1e-4, 1e-3):
            for seed in (0, 1):
                config = {"rep": {"name": rep, "out_dim": 10 if rep == "a" else 6},
                          "optim": {"lr": lr}, "seed": seed, "data": {"seed": seed},
                          "net": {"hidden": 16 + 16 * seed if hidden else 16},
                          "report": report}  # fmt: skip
                choices = {"rep": rep, "net": "pointnet", "loss": "chordal"}
                overrides = [f"rep={rep}", f"optim.lr={lr}", f"seed={seed}"]
                error = (1.0 if rep == "a" else 5.0) * (2.0 if lr > 5e-4 else 1.0) + seed
                _run(sweep / str(num), config, choices, overrides, error)
                num += 1


def test_every_swept_key_makes_its_own_setting_and_seeds_are_trials(tmp_path):
    _grid(tmp_path / "sweep")
    runs = collect_runs(tmp_path / "sweep")
    settings = [f"{rep} optim.lr={lr}" for rep in ("a", "sixd") for lr in ("0.0001", "0.001")]
    assert list(dict.fromkeys(runs["setting"])) == settings
    assert runs.groupby("setting").size().tolist() == [2, 2, 2, 2]
    report = make_report(tmp_path / "sweep")["report"].read_text()
    row = next(line for line in report.splitlines() if line.startswith("| a optim.lr=0.001 |"))
    assert row.split("|")[2].strip() == "2" and float(row.split("|")[4]) == 2.5  # 2 and 3
    assert "grouped by every config key that differs" in report


def test_group_by_and_pool_override_the_grouping(tmp_path):
    _grid(tmp_path / "sweep")
    by_rep = collect_runs(tmp_path / "sweep", group_by=["rep"])
    assert list(dict.fromkeys(by_rep["setting"])) == ["a", "sixd"]
    pooled = collect_runs(tmp_path / "sweep", pool=["optim.lr"])
    assert list(dict.fromkeys(pooled["setting"])) == ["a", "sixd"]
    seeds = collect_runs(tmp_path / "sweep", group_by=["seed", "optim.lr"])
    assert set(seeds["setting"]) == {f"optim.lr={lr} seed={s}" for lr in ("0.0001", "0.001")
                                     for s in (0, 1)}  # fmt: skip


def test_the_trial_keys_a_sweep_declares_are_pooled(tmp_path):
    """sweep=lr: each trial draws its own lr and seeds; the head alone makes the setting."""
    _grid(tmp_path / "sweep", report={"trial_keys": ["trial", "seed", "data.seed", "optim.lr"]})
    assert list(dict.fromkeys(collect_runs(tmp_path / "sweep")["setting"])) == ["a", "sixd"]


def test_a_key_swept_inside_one_config_group_is_named_by_the_key(tmp_path):
    """Two settings that share their config group options are told apart by the key."""
    _grid(tmp_path / "sweep", hidden=True)
    runs = collect_runs(tmp_path / "sweep", pool=["optim.lr"])
    assert set(runs["setting"]) == {f"{rep} net.hidden={h}" for rep in ("a", "sixd")
                                    for h in (16, 32)}  # fmt: skip


def test_an_evaluation_sits_beside_the_runs_it_evaluated(tmp_path):
    """`rotlearn-eval` writes evaluated.yaml: the config of the run it evaluated as that run
    keeps it, its config group choices (under `hydra`) and `evaluated.members`. The report
    labels the evaluation by what it changed and by the run's group options, not by every key
    of the evaluation's own config."""
    for num, (loss, seed) in enumerate([("bingham", 0), ("bingham", 1), ("chordal", 0)]):
        config = {
            "rep": {"name": "a"},
            "seed": seed,
            "model": {"head": "${rep}", "loss": "${loss}"},
            "loss": {"_target_": f"rotlearn.losses.{loss}", "rep": "${rep.name}"},
        }
        _run(tmp_path / "sweep" / str(num), config, {"rep": "a", "loss": loss},
             [f"loss={loss}", f"seed={seed}"], 1.0 + num)  # fmt: skip
    ensemble = tmp_path / "ensemble"
    _run(ensemble, {"ckpt": ["sweep/0", "sweep/1"], "ood": {"quantiles": None}}, {"sweep": "x"},
         ["ckpt=[sweep/0,sweep/1]"], 0.5)  # fmt: skip
    evaluated = yaml.safe_load((tmp_path / "sweep" / "0" / ".hydra" / "config.yaml").read_text())
    evaluated |= {"evaluated": {"members": 2},
                  "hydra": {"runtime": {"choices": {"rep": "a", "loss": "bingham"}}}}  # fmt: skip
    (ensemble / "evaluated.yaml").write_text(yaml.safe_dump(evaluated))
    runs = collect_runs([tmp_path / "sweep", ensemble])
    assert list(runs["setting"]) == [
        "a loss=bingham", "a loss=bingham", "a loss=chordal", "a evaluated.members=2 loss=bingham"
    ]  # fmt: skip


def test_values_that_read_alike_keep_their_settings_apart(tmp_path):
    """A label wrote a path by its last part, so data/demo/kitti and data/paper_scale/kitti both
    read `data.root=kitti` and their runs were pooled as one setting; such values are now
    written by as many of their last parts as tell them apart (numbers alike to 6 digits:
    in full)."""
    roots = ["/x/data/demo/kitti", "data/paper_scale/kitti"]
    lrs = [0.0010000001, 0.0010000002]
    for num, (root, lr, seed) in enumerate((r, lr, s) for r in roots for lr in lrs for s in (0, 1)):
        config = {"rep": {"name": "a"}, "data": {"root": root, "seed": seed}, "seed": seed,
                  "optim": {"lr": lr}}  # fmt: skip
        _run(tmp_path / "sweep" / str(num), config, {"rep": "a"}, [f"seed={seed}"], 1.0 + num)
    runs = collect_runs(tmp_path / "sweep")
    assert list(dict.fromkeys(runs["setting"])) == [
        f"a data.root={root} optim.lr={lr}"
        for root in ("demo/kitti", "paper_scale/kitti")
        for lr in ("0.0010000001", "0.0010000002")
    ]
    assert runs.groupby("setting").size().tolist() == [2, 2, 2, 2]


def test_a_null_value_and_an_absent_key_keep_their_settings_apart(tmp_path):
    """A label leaves out a key a run does not have, and it left out a null value too, so a run
    with `scheduler: null` and one without a scheduler key read alike and were pooled; where
    both occur, the null one says `scheduler=null`."""
    for num, scheduler in enumerate(({"scheduler": None}, {}, {"scheduler": {"gamma": 0.5}})):
        config = {"rep": {"name": "a"}, **scheduler}
        _run(tmp_path / "sweep" / str(num), config, {"rep": "a"}, [], 1.0)
    runs = collect_runs(tmp_path / "sweep")
    assert list(runs["setting"]) == ["a scheduler=null", "a", "a scheduler.gamma=0.5"]


def test_a_class_that_tells_runs_apart_is_named_by_its_class(tmp_path):
    """Where no config group option says it, a differing `_target_` reads as the class name."""
    for num, loss in enumerate(("BinghamNLLLoss", "ChordalLoss")):
        config = {"rep": {"name": "a"}, "loss": {"_target_": f"rotlearn.losses.{loss}"}}
        _run(tmp_path / "sweep" / str(num), config, {}, [], 1.0)
    assert list(collect_runs(tmp_path / "sweep")["setting"]) == [
        "a loss=BinghamNLLLoss", "a loss=ChordalLoss"
    ]  # fmt: skip


def test_an_auto_encoder_run_is_reported_by_its_reconstruction_error(tmp_path):
    """The auto-encoder (model=autoencoder) takes no head and no loss: its label is not the
    unused `rep` it was composed with, its summary has no rep or loss column, and the report
    counts it completed with a table of its test reconstruction error."""
    choices = {"model": "autoencoder", "rep": "a", "loss": "chordal", "net": "autoencoder"}
    for num, lr in enumerate((1e-4, 1e-3)):
        config = {
            "model": {"net": "${net}", "optimizer": "${optim}"},
            "rep": {"name": "a"},
            "loss": {"_target_": "rotlearn.losses.ChordalLoss"},
            "optim": {"lr": lr},
        }
        run = tmp_path / "sweep" / str(num)
        _run(run, config, choices, [f"optim.lr={lr}"], 0.0)
        (run / "metrics.json").write_text(json.dumps({"test/recon_mean": 0.25 * (num + 1)}))
    runs = collect_runs(tmp_path / "sweep")
    assert list(runs["setting"]) == ["optim.lr=0.0001", "optim.lr=0.001"]
    assert not [c for c in runs if c.startswith(("rep", "loss", "group:rep", "group:loss"))]
    report = make_report(tmp_path / "sweep")["report"].read_text()
    assert "2 jobs: 2 completed." in report
    assert "| optim.lr=0.001 | 0.500 |" in report  # one run a setting: its number, once
    single = collect_runs(tmp_path / "sweep" / "0")
    assert list(single["setting"]) == ["autoencoder"]


def test_a_run_given_twice_is_reported_once_and_a_damaged_status_is_ignored(tmp_path, caplog):
    """`rotlearn-report <sweep> <sweep>` or `<sweep> <sweep>/0` counts each run once; a
    status.json whose status is no string (a received run) is ignored with a warning, not a
    traceback."""
    _grid(tmp_path / "sweep")
    sweep = tmp_path / "sweep"
    assert len(collect_runs([sweep, sweep])) == len(collect_runs([sweep, sweep / "0"])) == 8
    (sweep / "0" / "status.json").write_text(json.dumps({"status": 7}))
    report = make_report(sweep)["report"].read_text()
    assert "8 jobs: 8 completed." in report  # its metrics.json says it finished
    assert "status.json: status is not a string; ignored" in caplog.text


def test_group_by_a_key_no_run_has_is_refused_naming_the_nearest(tmp_path, capsys):
    """--group-by nosuch pooled every run into one row before; now it is refused in one line."""
    from rotlearn.cli.report import main

    _grid(tmp_path / "sweep")
    with pytest.raises(ValueError, match=r"--group-by optim\.lrr: no run has this config key; "
                       r"did you mean optim\.lr\?"):  # fmt: skip
        collect_runs(tmp_path / "sweep", group_by=["optim.lrr"])
    assert main([str(tmp_path / "sweep"), "--group-by", "nosuch.key"]) == 2
    assert capsys.readouterr().err == (
        "rotlearn-report: --group-by nosuch.key: no run has this config key\n"
    )
    assert not (tmp_path / "sweep" / "report.md").exists()


@pytest.mark.parametrize("damage", ["deleted", "emptied"])
def test_a_run_whose_config_is_lost_is_reported_apart_and_named(tmp_path, caplog, damage):
    """A run whose .hydra/config.yaml was deleted was left out of the report without a word; an
    emptied one made every key of the others' configs 'differ', so each label listed them all.
    Now either is one '(config unreadable)' row, with a warning naming the file, and the other
    runs keep their labels."""
    _grid(tmp_path / "sweep")
    config = tmp_path / "sweep" / "3" / ".hydra" / "config.yaml"
    config.unlink() if damage == "deleted" else config.write_text("")
    runs = collect_runs(tmp_path / "sweep")
    assert len(runs) == 8 and runs.loc[runs["job"] == "3", "setting"].item() == (
        "(config unreadable)"
    )
    others = {
        "a optim.lr=0.0001",
        "a optim.lr=0.001",
        "sixd optim.lr=0.0001",
        "sixd optim.lr=0.001",
    }
    assert set(runs.loc[runs["job"] != "3", "setting"]) == others
    assert f"{config}: missing, empty, refused or not a mapping" in caplog.text


def test_report_refuses_a_root_or_out_that_is_no_folder_in_one_line(tmp_path, capsys):
    from rotlearn.cli.report import main

    _grid(tmp_path / "sweep")
    file = tmp_path / "notes.txt"
    file.write_text("x\n")
    cases = {
        (str(file),): f"{file}: not a folder; pass a sweep or run directory",
        (str(tmp_path / "nosuch"),): f"{tmp_path / 'nosuch'}: no such folder; pass a sweep or run",
        (str(tmp_path / "sweep"), "--out", str(file)): f"--out {file}: a file is there; pass a",
    }
    for args, message in cases.items():
        assert main(list(args)) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"rotlearn-report: {message}") and err.count("\n") == 1
    assert file.read_text() == "x\n" and not (tmp_path / "sweep" / "report.md").exists()
