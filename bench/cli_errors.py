"""How fast a command line's mistake is answered (issue 23; target: 2 s on an idle 2-core machine).

Each case runs its command in a fresh process in an empty working directory and measures the
wall-clock seconds until it exits, refusing in one line. The folders some cases name are made
first (`scenario`): a folder that is no run, a sweep directory with two jobs, a run of synthetic
data (its checkpoint carries the config; no weights are needed to refuse it) and a KITTI folder
with only sequence 00. Unknown keys, options, values, data folders and a run's data are decided
from files alone (the sources, the checkpoint's config read without torch); the rules that span
keys build the head and the loss (torch, not Lightning).
`make bench ARGS=cli_errors`; tests/cli/test_errors.py runs the same cases.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
TARGET_S = 2.0
PROGRAMS = {
    "rotlearn-train": "rotlearn.train",
    "rotlearn-eval": "rotlearn.cli.evaluate",
    "rotlearn-predict": "rotlearn.cli.predict",
}
# name -> (program, arguments); {folder} names a folder of `scenario`
CASES: dict[str, tuple[str, list[str]]] = {
    "misspelt key": ("rotlearn-train", ["optim.lrr=1e-3"]),
    "misspelt key with +": ("rotlearn-train", ["+optim.lrr=1e-3"]),
    "a component's key at the top level": ("rotlearn-train", ["lr=1e-3"]),
    "the README's misspelt key": ("rotlearn-train", ["data.phi_maxdeg=10"]),
    "a misspelt key to delete": ("rotlearn-train", ["~optim.lrr"]),
    "a misspelt key in a mapping": ("rotlearn-train", ["optim={{lrr: 1e-3}}"]),
    "unknown option": ("rotlearn-train", ["rep=aa"]),
    "a schema as an option": ("rotlearn-train", ["rep=head_schema"]),
    "no data root": ("rotlearn-train", ["data=kitti", "data.root=/nonexistent"]),
    "incomplete dataset": ("rotlearn-train", ["data=kitti", "data.root={kitti}"]),
    "an override the grammar cannot read": ("rotlearn-train", ["optim.lr=[1"]),
    "a run folder for a sweep": ("rotlearn-train", ["-m", "rep=a,sixd", "hydra.run.dir=new"]),
    "a sweep folder for one run": ("rotlearn-train", ["hydra.sweep.dir=new"]),
    "a misspelt key of Hydra's": ("rotlearn-train", ["hydra.run.dirr=new"]),
    "a setting of another launcher": ("rotlearn-train", ["hydra.launcher.n_jobs=2"]),
    "a sweep's config asked for": ("rotlearn-train", ["-m", "rep=a,sixd", "--cfg", "job"]),
    "a sweep of Hydra's own settings": (
        "rotlearn-train",
        ["-m", "sweep=seeds", "hydra.sweeper.params.trial=range(0,5)"],
    ),
    "value out of range": ("rotlearn-train", ["data.batch_size=0"]),
    "no demo data": ("rotlearn-train", ["experiment=mav_ood_demo"]),
    "no data root of this format": ("rotlearn-train", ["data=shapenet", "data.root=/nonexistent"]),
    "a misspelt option in a sweep": ("rotlearn-train", ["-m", "rep=a,sixx"]),
    "a sweep's second value out of range": ("rotlearn-train", ["-m", "data.phi_max_deg=90,270"]),
    "sweep values that do not go together": (
        "rotlearn-train",
        ["-m", "rep=a,sixd", "loss=chordal,bingham"],
    ),
    "a value of the wrong type": ("rotlearn-train", ["optim.lr=abc"]),
    "a Trainer value out of range": ("rotlearn-train", ["trainer.max_epochs=0"]),
    "an accelerator the machine lacks": ("rotlearn-train", ["trainer.accelerator=tpu"]),
    "null for a config group": ("rotlearn-train", ["logger=null"]),
    "a group the config chooses none of": ("rotlearn-train", ["variant=a_bingham"]),
    "calibrate without a belief": ("rotlearn-train", ["rep=sixd", "calibrate=true"]),
    "likelihood loss without a belief": ("rotlearn-train", ["rep=sixd", "loss=bingham"]),
    "eval without ckpt": ("rotlearn-eval", []),
    "eval with an empty ckpt": ("rotlearn-eval", ["ckpt="]),
    "eval with an unclosed list of runs": ("rotlearn-eval", ["ckpt=[{not_a_run},{sweep}"]),
    "eval of a folder that is no run": ("rotlearn-eval", ["ckpt={not_a_run}"]),
    "eval of a sweep directory": ("rotlearn-eval", ["ckpt={sweep}"]),
    "eval with OOD on synthetic data": ("rotlearn-eval", ["ckpt={synthetic_run}"]),
    "eval with a dataset option": ("rotlearn-eval", ["ckpt={synthetic_run}", "data=kitti"]),
    "eval with no mapping for ood": ("rotlearn-eval", ["ckpt={synthetic_run}", "ood=null"]),
    "predict with a folder that is no run": ("rotlearn-predict", ["{not_a_run}", "pairs.txt"]),
    "predict with a sweep directory": ("rotlearn-predict", ["{sweep}", "pairs.txt"]),
    "predict with a folder of runs": ("rotlearn-predict", ["{runs}", "pairs.txt"]),
}


def scenario(root: Path) -> dict[str, str]:
    """Make the folders the cases name under `root`; returns name -> path."""
    import torch

    from rotlearn.config import compose
    from rotlearn.config.checks import plain

    paths = {name: root / name for name in ("not_a_run", "sweep", "synthetic_run", "kitti")}
    paths["runs"] = root  # a folder of runs that is no sweep, as outputs/ is
    paths["not_a_run"].mkdir(parents=True)
    (paths["not_a_run"] / "notes.txt").write_text("not a run\n")
    for job in ("0", "1"):
        ckpt = paths["sweep"] / job / "checkpoints" / "last.ckpt"
        ckpt.parent.mkdir(parents=True)
        ckpt.write_bytes(b"")
    (paths["sweep"] / "multirun.yaml").write_text("{}\n")
    config = plain(compose(["data=tiny"], output_dir=paths["synthetic_run"]))
    ckpt = paths["synthetic_run"] / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    torch.save({"rotlearn_config": config, "state_dict": {}, "epoch": 0}, ckpt)
    (paths["kitti"] / "sequences" / "00" / "image_2").mkdir(parents=True)
    (paths["kitti"] / "poses").mkdir()
    (paths["kitti"] / "poses" / "00.txt").write_text("")
    return {name: str(path) for name, path in paths.items()}


def run(name: str, paths: dict[str, str], cwd: Path) -> tuple[subprocess.CompletedProcess, float]:
    """Run case `name` in `cwd`: its completed process and wall-clock seconds."""
    program, args = CASES[name]
    command = [sys.executable, "-m", PROGRAMS[program], *(a.format(**paths) for a in args)]
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore"}
    start = time.perf_counter()
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    return done, time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    from rotlearn.io import write_json_atomic
    from timing import machine

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths = scenario(Path(tmp) / "folders")
        for name in CASES:
            times = []
            for i in range(args.repeats):
                cwd = Path(tmp) / f"cwd-{len(rows)}-{i}"
                cwd.mkdir()
                done, seconds = run(name, paths, cwd)
                times.append(seconds)
            line = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ""
            rows[name] = {
                "median_s": statistics.median(times),
                "exit_code": done.returncode,
                "message": line,
            }
    print(f"\nSeconds until a refused command exits (median of {args.repeats}; target {TARGET_S})")
    for name, row in rows.items():
        mark = "" if row["median_s"] <= TARGET_S else "  (over the target)"
        print(f"{name:38s} {row['median_s']:6.2f}{mark}")
    result = {"machine": machine("cpu"), "target_s": TARGET_S, "result": rows}
    path = write_json_atomic(RESULTS / "cli_errors.json", result)
    print(f"-> {path}")


if __name__ == "__main__":
    main()
