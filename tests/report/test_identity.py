"""What tells runs apart (rotlearn.report.identity): names and HPARAMS records from overrides."""

from __future__ import annotations

from rotlearn.report.identity import hparams_record, run_name, short_value, swept_keys

CONFIG = {
    "rep": {"name": "a"},
    "optim": {"lr": 0.001},
    "seed": 0,
    "calibrate": False,
    "trainer": {"max_epochs": 3},
    "data": {"_target_": "rotlearn.data.SyntheticWahbaDataModule", "root": "/data/kitti/"},
    "net": {"point_channels": [16, 32]},
    "callbacks": {"checkpoint": {"dirpath": "/x"}},
}
CHOICES = {"rep": "a", "loss": "chordal", "net": "pointnet", "data": "tiny", "trainer": "cpu"}


def test_a_run_is_named_by_its_overrides_in_their_shortest_form():
    overrides = ["rep=a", "optim.lr=1e-3", "trainer.max_epochs=3", "hydra.run.dir=/tmp/x",
                 "callbacks.checkpoint.dirpath=/y", "logger=csv", "+calibrate=false"]  # fmt: skip
    assert run_name(CONFIG, overrides, CHOICES) == (
        "rep=a,optim.lr=0.001,trainer.max_epochs=3,calibrate=false"
    )
    # in a sweep, only what the sweep varies
    assert run_name(CONFIG, overrides, CHOICES, keys=["rep", "optim.lr"]) == "rep=a,optim.lr=0.001"
    assert run_name(CONFIG, [], CHOICES) == "defaults"
    # what the terminal shows is no setting (make reproduce-ood turns the progress bar off)
    quiet = ["rep=a", "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]
    assert run_name(CONFIG, quiet, CHOICES) == "rep=a"
    assert "trainer.enable_progress_bar" not in hparams_record(CONFIG, quiet, CHOICES)
    assert run_name(CONFIG, ["data.root=/data/kitti/"], CHOICES) == "data.root=kitti"
    # a list typed on the command line (rotlearn-eval's ensembles), item by item: no "2]"
    ensemble = "ckpt=[outputs/sweep/0,outputs/sweep/1,outputs/sweep/2/]"
    assert run_name({}, [ensemble]) == "ckpt=[0,1,2]"
    long = run_name({}, [f"k{i}=value{i}" for i in range(40)])
    assert len(long) == 120 and "/" not in long and long != run_name({}, ["k0=other"] * 40)


def test_the_hparams_record_holds_the_headline_and_every_override_but_plumbing():
    overrides = ["trainer=cpu", "optim.lr=1e-3", "net.point_channels=[16,32]", "+calibrate=false",
                 "callbacks=ood", "callbacks.ood.noise_pairs=4", "logger.tensorboard.name=tb",
                 "ckpt_path=last", "paths.output_dir=/x"]  # fmt: skip
    record = hparams_record(CONFIG, overrides, CHOICES)
    assert list(record)[:6] == ["rep", "loss", "net", "data", "optim.lr", "seed"]
    assert record == {"rep": "a", "loss": "chordal", "net": "pointnet", "data": "tiny",
                      "optim.lr": 0.001, "seed": 0, "trainer": "cpu",
                      "net.point_channels": "[16,32]", "calibrate": False}  # fmt: skip
    assert isinstance(record["calibrate"], bool)  # shown as false, not 0.0000
    # without Hydra's runtime (a config composed in Python): the head's name and the classes
    bare = hparams_record(CONFIG, [])
    assert bare["rep"] == "a" and bare["data"] == "SyntheticWahbaDataModule"


def test_swept_keys_are_those_whose_value_differs_between_jobs():
    jobs = [["rep=a", "optim.lr=1e-4", "data=tiny"], ["rep=a", "optim.lr=1e-3", "data=tiny"],
            ["rep=sixd", "optim.lr=1e-4", "data=tiny", "hydra.job.chdir=true"]]  # fmt: skip
    assert swept_keys(jobs) == ["rep", "optim.lr"]
    assert short_value(1e-4) == "0.0001" and short_value(True) == "true"
