"""rotlearn benchmarks: `make bench [ARGS="epoch heads paper"]`.

- epoch: seconds per epoch of the paper's synthetic setting (5 x 100 training samples, 100 matches,
  validation on 100), per representation, through the real Lightning pipeline; `--device cuda`
  trains with trainer=gpu (bf16-mixed where the GPU has bfloat16), `--overrides` changes the
  setting (e.g. "data.batch_size=4096 data.batches_per_epoch=20"); the A / 6D ratio of the
  epoch times is the cost of the A head in a whole training epoch (issue 26: within 10 % on GPU).
- heads: microseconds per sample of each head's forward and forward+backward at a large batch.
- a_layer: the A layer (10 numbers -> q, forward+backward) on its fused kernel (C on the CPU,
  Triton on CUDA) and eager path against torch.linalg.eigh, roma, 6D and SVD-9D at B = 1 ... 1M,
  float32 (and bf16 autocast on CUDA), with the eigh/rotlearn ratio (bench/a_layer.py; issues 16,
  26); `--device cuda` for the GPU.
- bingham: log N(Lambda) and its gradient per sample (bench/bingham.py).
- kitti_loader: first-time KITTI preprocessing rate and cached pairs/s with 2 workers
  (bench/kitti_loader.py).
- cli_errors: seconds until a command line's mistake is refused (unknown key or option, missing
  data, a folder that is no run, ...), each in a fresh process (bench/cli_errors.py; issue 23).
- text_readers: peak memory per byte of the dataset text readers (MAV CSVs, KITTI poses) on the
  shortest rows each accepts, as a hostile dataset would write them (bench/text_readers.py).
- predictor: peak memory (RSS) and seconds of `rotlearn.inference.Predictor` on 10k and 100k
  samples of 10 point pairs (PointNet + A head), each in a fresh process: chunking bounds memory.
- paper: the paper's synthetic experiment (lr 5e-4, 50 epochs, phi_max 180) over 3 seeds per
  representation (`--seeds 1-9` for more), beside the numbers of the authors' code (issue 2): the
  median and mean over seeds, the 95 % interval of the mean, and whether that interval lies
  below, level with or above the authors' value.

Each benchmark prints a table and writes bench/results/<name>.json. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import statistics
import sys
import tempfile
import warnings
from pathlib import Path

import torch

from rotlearn.cli.train import train
from rotlearn.config import compose
from rotlearn.heads import HEADS, make_head
from rotlearn.io import write_json_atomic
from timing import PEAK_RSS, machine, median_seconds

RESULTS = Path(__file__).resolve().parent / "results"
QUIET = ["trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]
# The authors' code on this machine (issue 2): final test mean error (deg) and seconds per epoch.
AUTHORS = {"a": ("1.1-1.4", "0.735"), "sixd": ("1.6", "0.71"), "quat": ("6.6-16", "0.71-0.75")}


def _machine(device: str = "cpu") -> dict:
    return machine(device) | {
        "cuda": torch.version.cuda,
        "load_average": list(os.getloadavg()),
    }


def _run(overrides: list[str], out: Path) -> dict:
    """Train one config; its metrics.json plus the epoch time from timing.json."""
    metrics = train(compose([*QUIET, *overrides], output_dir=out))
    timing = json.loads((out / "timing.json").read_text())
    return {**metrics, "epoch_time_s": timing["epoch_time_s"]}


def bench_epoch(
    reps: list[str], epochs: int = 6, device: str = "cpu", overrides: list[str] | None = None
) -> dict:
    trainer = "gpu" if device.startswith("cuda") else "cpu"
    overrides = overrides or []
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in reps:
            run = [f"rep={rep}", f"trainer={trainer}", f"trainer.max_epochs={epochs}", *overrides]
            m = _run(run, Path(tmp) / rep)
            rows[rep] = {"epoch_time_s": m["epoch_time_s"], "epochs_timed": epochs - 1}
    setting = " ".join(overrides) or "5 x 100 samples + validation on 100"
    print(f"\nSeconds per epoch, trainer={trainer} ({setting}; mean of epochs 2-{epochs})")
    print(f"{'rep':8s} {'rotlearn':>10s} {'authors':>10s}")
    for rep, row in rows.items():
        authors = AUTHORS.get(rep, ("", "-"))[1] if trainer == "cpu" and not overrides else "-"
        print(f"{rep:8s} {row['epoch_time_s']:10.3f} {authors:>10s}")
    result = {"trainer": trainer, "overrides": overrides, "reps": rows}
    if "a" in rows and "sixd" in rows:
        result["a_over_sixd"] = rows["a"]["epoch_time_s"] / rows["sixd"]["epoch_time_s"]
        print(f"A / 6D epoch time: {result['a_over_sixd']:.3f}")
    return result


def bench_heads(batch: int = 131072) -> dict:
    rows = {}
    gen = torch.Generator().manual_seed(0)
    for name in sorted(HEADS):
        head = make_head(name)
        raw = torch.randn(batch, head.out_dim, generator=gen)

        def forward(head=head, raw=raw):
            with torch.no_grad():
                return head(raw).R

        def backward(head=head, raw=raw):
            x = raw.clone().requires_grad_(True)
            head(x).R.sum().backward()

        rows[name] = {
            "forward_us": 1e6 * median_seconds(forward) / batch,
            "forward_backward_us": 1e6 * median_seconds(backward) / batch,
        }
    print(f"\nHeads, float32, batch {batch}: microseconds per sample")
    print(f"{'rep':8s} {'forward':>10s} {'fwd+bwd':>10s}")
    for name, row in rows.items():
        print(f"{name:8s} {row['forward_us']:10.3f} {row['forward_backward_us']:10.3f}")
    return {"batch": batch, "heads": rows}


_PREDICTOR_RUN = (
    PEAK_RSS
    + """
import sys, time, torch
from rotlearn.heads import make_head
from rotlearn.inference import Predictor
from rotlearn.nets import PointNet
torch.manual_seed(0)
predictor = Predictor(PointNet(out_dim=10), make_head("a", 10))
x = torch.randn(int(sys.argv[1]), 10, 6)
start = time.perf_counter()
predictor(x)
seconds = time.perf_counter() - start
print(peak_rss() / 2**30, seconds)
"""
)


def bench_predictor(batches: tuple[int, ...] = (10_000, 100_000)) -> dict:
    import subprocess

    rows = {}
    for batch in batches:
        done = subprocess.run(
            [sys.executable, "-c", _PREDICTOR_RUN, str(batch)],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        peak_gb, seconds = map(float, done.stdout.split())
        rows[batch] = {"peak_rss_gb": peak_gb, "seconds": seconds}
    print("\nPredictor (PointNet + A head), 10 point pairs per sample: peak RSS of the process")
    print(f"{'samples':>8s} {'peak GB':>8s} {'seconds':>8s}")
    for batch, row in rows.items():
        print(f"{batch:8d} {row['peak_rss_gb']:8.2f} {row['seconds']:8.1f}")
    return {"pairs_per_sample": 10, "batches": rows}


def mean_interval(values: list[float], level: float = 0.95) -> tuple[float, float]:
    """The two-sided Student-t confidence interval of the mean of `values` (n >= 2)."""
    from scipy.stats import t  # dev extra

    mean = statistics.mean(values)
    half = t.ppf(0.5 + level / 2, len(values) - 1) * statistics.stdev(values) / len(values) ** 0.5
    return float(mean - half), float(mean + half)


def verdict(low: float, high: float, authors: str) -> str:
    """Where a 95 % interval of our mean lies against the authors' value or range "a-b":
    below / level (it overlaps) / above."""
    bounds = [float(x) for x in authors.split("-")]
    if high < bounds[0]:
        return "below"
    return "above" if low > bounds[-1] else "level"


def bench_paper(reps: list[str], seeds: list[int]) -> dict:
    rows: dict[str, list[dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in reps:
            for seed in seeds:
                out = Path(tmp) / f"{rep}-{seed}"
                m = _run([f"rep={rep}", "trainer=cpu", f"seed={seed}", f"data.seed={seed}"], out)
                rows.setdefault(rep, []).append(
                    {k: m[k] for k in ("test/err_mean", "test/err_median", "epoch_time_s")}
                    | {"seed": seed}
                )
                print(f"  {rep} seed {seed}: {m['test/err_mean']:.3f} deg", flush=True)
    print("\nPaper synthetic setting (lr 5e-4, 50 epochs, phi_max 180): final test mean error, deg")
    print(f"seeds {','.join(map(str, seeds))}; interval: 95 % Student-t interval of the mean")
    header = f"{'rep':6s} {'median':>7s} {'mean':>6s} {'95% interval':>14s} {'authors':>8s}"
    print(f"{header} {'verdict':>8s} {'s/epoch':>8s}")
    summary = {}
    for rep, runs in rows.items():
        errs = [r["test/err_mean"] for r in runs]
        epoch = statistics.mean(r["epoch_time_s"] for r in runs)
        authors = AUTHORS.get(rep, ("-", "-"))[0]
        row = {"median": statistics.median(errs), "mean": statistics.mean(errs)}
        interval, judged = "-", "-"
        if len(errs) > 1:
            low, high = mean_interval(errs)
            row["interval"] = [low, high]
            interval = f"{low:.2f}-{high:.2f}"
            judged = verdict(low, high, authors) if authors != "-" else "-"
        summary[rep] = row | {"verdict": judged}
        print(
            f"{rep:6s} {row['median']:7.2f} {row['mean']:6.2f} {interval:>14s} {authors:>8s} "
            f"{judged:>8s} {epoch:8.3f}"
        )
    return {"runs": rows, "summary": summary, "authors": AUTHORS}


def parse_seeds(text: str) -> list[int]:
    """ "1,2,3" or "1-9" or "0,4-6" -> a list of seeds."""
    seeds: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds.extend(range(int(first), int(last or first) + 1))
    return seeds


SCRIPTS = {
    "a_layer": "a_layer.py",
    "bingham": "bingham.py",
    "rep_layers": "rep_layers.py",
    "kitti_loader": "kitti_loader.py",
    "cli_errors": "cli_errors.py",
    "text_readers": "text_readers.py",
}  # benchmarks with their own CLI
DEVICE_SCRIPTS = ("a_layer", "rep_layers")  # those that take --device (the others run on CPU)


def _run_script(name: str, device: str, extra: list[str]) -> None:
    path = Path(__file__).resolve().parent / SCRIPTS[name]
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main([*(["--device", device] if name in DEVICE_SCRIPTS else []), *extra])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    scripts = [n for n, f in SCRIPTS.items() if (RESULTS.parent / f).exists()]
    default = ["epoch", "heads", "predictor", *scripts]
    parser.add_argument("names", nargs="*", default=default, help="epoch heads bingham paper ...")
    parser.add_argument("--reps", default="a,sixd,quat")
    parser.add_argument("--seeds", default="1,2,3", help='"1,2,3" or "1-9"')
    parser.add_argument(
        "--device", default="cpu", help=f"cpu or cuda, for epoch, {', '.join(DEVICE_SCRIPTS)}"
    )
    parser.add_argument("--epochs", type=int, default=6, help="epoch: epochs per run")
    parser.add_argument(
        "--overrides", default="", help='epoch: Hydra overrides, e.g. "data.batch_size=4096"'
    )
    parser.add_argument("--out", type=Path, default=None, help="epoch/heads/...: the JSON path")
    # Options this parser does not know go to the one script benchmark named, e.g.
    # `make bench ARGS="a_layer --threads 1 --clock cpu"`.
    args, extra = parser.parse_known_args(argv)
    if extra and not (len(args.names) == 1 and args.names[0] in SCRIPTS):
        parser.error(
            f"unrecognized arguments {' '.join(extra)} (options of a script benchmark"
            f" go with it alone, e.g. a_layer --threads 1)"
        )
    warnings.filterwarnings("ignore")
    logging.getLogger("lightning").setLevel(logging.ERROR)
    logging.getLogger("lightning.pytorch").setLevel(logging.ERROR)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        sys.exit(f"--device {args.device}: torch.cuda.is_available() is False on this machine")
    reps = args.reps.split(",")
    seeds = parse_seeds(args.seeds)
    benches = {
        "epoch": lambda: bench_epoch(reps, args.epochs, args.device, args.overrides.split()),
        "heads": bench_heads,
        "predictor": bench_predictor,
        "paper": lambda: bench_paper(reps, seeds),
    }
    unknown = set(args.names) - set(benches) - set(SCRIPTS)
    if unknown:
        sys.exit(
            f"unknown benchmark(s) {sorted(unknown)}; choose from {sorted([*benches, *SCRIPTS])}"
        )
    for name in args.names:
        if name in SCRIPTS:
            out = ["--out", str(args.out)] if args.out else []
            _run_script(name, args.device, [*out, *extra])
            continue
        device = args.device if name == "epoch" else "cpu"
        result = {"machine": _machine(device), "result": benches[name]()}
        tag = name if device == "cpu" else f"{name}_{torch.device(device).type}"
        path = write_json_atomic(args.out or RESULTS / f"{tag}.json", result)
        print(f"-> {path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path}")


if __name__ == "__main__":
    main()
