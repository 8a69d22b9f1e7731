"""The A layer against torch.linalg.eigh, roma, 6D and SVD-9D: microseconds per sample (issue 26).

Every layer maps its raw network output to a rotation, forward and backward:
- rotlearn: 10 numbers -> a_from_vec -> sym4_eigh_min(check=False) -> q, as the A head runs it
  (method and kernel "auto": the Jacobi solver on the fused kernel of the device where it runs,
  the C kernel on the CPU and the Triton kernels on CUDA; the path is printed and in the JSON);
- jacobi_eager: the same on the eager path (PyTorch tensor operations, ~450 kernels per call);
- eigh_fwd: torch.linalg.eigh's forward with rotlearn's backward (method="eigh");
- eigh: 10 numbers -> a_from_vec -> torch.linalg.eigh -> V[..., 0], plain autograd (NaN gradients
  at repeated eigenvalues; no canonical sign, the cheapest eigh can be);
- roma: roma.symmatrixvec_to_unitquat (eigh inside; skipped with a note when `import roma` fails);
  eigh and roma get their input as float32 (eigh has no bfloat16 kernel);
- sixd: rotlearn.geometry.sixd_to_rotmat on 6 numbers; svd9d: special_orthogonalize on 9 numbers.
The backward is that of a fixed random linear function of the output (autograd.grad to the raw
input). Ratios: eigh / rotlearn and roma / rotlearn (> 1: rotlearn is faster), rotlearn / sixd.
Modes: float32, and bf16-amp (the layer called under torch.autocast(bfloat16) on bfloat16 input:
the rotation maps compute in float32 there) on CUDA or with --autocast.

Timing: the layers are timed in turn within each repeat (interleaved), so a change of machine load
hits all of them alike; the table shows medians, the JSON also min and max over the repeats.
`--clock cpu` times the CPU seconds of this process (time.process_time) instead of wall-clock
seconds: on a shared machine, with --threads 1, it leaves out the time other processes hold the
core (on CUDA the clock is always wall-clock with synchronisation).

    .venv/bin/python bench/a_layer.py                                  # CPU, B = 1 ... 1M
    .venv/bin/python bench/a_layer.py --threads 1 --clock cpu          # per-core, shared machine
    .venv/bin/python bench/a_layer.py --device cuda                    # GPU, also bf16 autocast
    .venv/bin/python bench/a_layer.py --batches 100,16384 --repeats 9

Written to bench/results/a_layer_<device>[_<threads>t].json with the CPU model, the thread count,
the GPU name, the torch, CUDA and Triton versions, the path that ran and the load average before
and after.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from rotlearn.geometry import a_from_vec, sixd_to_rotmat, special_orthogonalize
from rotlearn.geometry.eigen4 import EIGH_BELOW, sym4_eigh_min
from rotlearn.geometry.eigen4.ops import resolve_kernel
from rotlearn.io import write_json_atomic
from timing import machine

RESULTS = Path(__file__).resolve().parent / "results"
BATCHES = {
    "cpu": "1,32,100,1024,16384,131072,1048576",
    "cuda": "32,100,1024,4096,16384,131072,1048576",
}

try:
    import roma
except ImportError:  # optional: the table notes its absence
    roma = None


def _rotlearn(method: str, kernel: str) -> Callable[[Tensor], Tensor]:
    def layer(x: Tensor) -> Tensor:
        return sym4_eigh_min(a_from_vec(x), check=False, method=method, kernel=kernel)[1]

    return layer


def _eigh(x: Tensor) -> Tensor:
    # .float(): eigh has no bfloat16 kernel (a no-op for float32 input)
    return torch.linalg.eigh(a_from_vec(x.float())).eigenvectors[..., 0]


LAYERS: dict[str, tuple[int, Callable[[Tensor], Tensor]]] = {
    "rotlearn": (10, _rotlearn("auto", "auto")),
    "jacobi_eager": (10, _rotlearn("jacobi", "eager")),
    "eigh_fwd": (10, _rotlearn("eigh", "auto")),
    "eigh": (10, _eigh),
    "sixd": (6, sixd_to_rotmat),
    "svd9d": (9, lambda x: special_orthogonalize(x.unflatten(-1, (3, 3)))),
}
if roma is not None:
    LAYERS["roma"] = (10, lambda x: roma.symmatrixvec_to_unitquat(x.float()))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _clock(kind: str, device: torch.device) -> Callable[[], float]:
    return time.process_time if kind == "cpu" and device.type == "cpu" else time.perf_counter


def bench_batch(
    batch: int, device: torch.device, args: argparse.Namespace, autocast: bool, names: list[str]
) -> dict[str, dict]:
    """Forward+backward seconds per call of every layer at one batch size, interleaved."""
    gen = torch.Generator(device=device).manual_seed(0)
    clock = _clock(args.clock, device)
    dtype = torch.bfloat16 if autocast else torch.float32
    calls = {}
    errors: dict[str, str] = {}
    for name in names:
        dim, layer = LAYERS[name]
        leaf = torch.randn(batch, dim, generator=gen, device=device).to(dtype).requires_grad_(True)
        try:  # a layer that fails (a dtype it refuses, a library's batch limit) is one cell
            with (
                torch.no_grad(),
                torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast),
            ):
                weight = torch.randn_like(layer(leaf), dtype=torch.float32)
        except Exception as error:
            errors[name] = f"{type(error).__name__}: {error}"[:200]
            continue

        def call(layer=layer, leaf=leaf, weight=weight):
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
                out = layer(leaf)
            return torch.autograd.grad((out.float() * weight).sum(), leaf)

        calls[name] = call
    times: dict[str, list[float]] = {name: [] for name in calls}
    inner = {}
    for name, call in calls.items():  # warm-up, and how many calls fill the budget
        try:
            call()
            _sync(device)
            start = clock()
            call()
            _sync(device)
            inner[name] = max(1, int(args.budget / max(clock() - start, 1e-7)))
        except Exception as error:  # e.g. a dtype that a layer refuses under autocast
            errors[name] = f"{type(error).__name__}: {error}"[:200]
    for _ in range(args.repeats):
        for name, call in calls.items():
            if name in errors:
                continue
            _sync(device)
            start = clock()
            for _ in range(inner[name]):
                call()
            _sync(device)
            times[name].append((clock() - start) / inner[name])
    rows = {}
    for name in names:
        if name in errors:
            rows[name] = {"error": errors[name]}
            continue
        us = [1e6 * t / batch for t in times[name]]
        rows[name] = {
            "median_us": statistics.median(us),
            "min_us": min(us),
            "max_us": max(us),
            "calls_per_repeat": inner[name],
        }
    return rows


def _ratio(rows: dict[str, dict], num: str, den: str) -> float | None:
    if "median_us" not in rows.get(num, {}) or "median_us" not in rows.get(den, {}):
        return None
    return rows[num]["median_us"] / rows[den]["median_us"]


RATIOS = (("eigh", "rotlearn"), ("roma", "rotlearn"), ("rotlearn", "sixd"))


def targets(results: list[dict], device: str) -> list[str]:
    """Issue 26's speed targets, each with the measured ratio and by how much it is met or missed.

    CPU (float32): 1. never slower than plain eigh with autograd at any batch size (eigh/rotlearn
    >= 1 everywhere); 2. eigh/rotlearn >= 8 at B >= 16384 (goal 10). CUDA (float32): eigh/rotlearn
    >= 50 at B = 4096; rotlearn/sixd <= 2 at every batch size."""

    def worst(pairs: list[tuple[int, float]], low: bool = True) -> tuple[int, float] | None:
        return (min if low else max)(pairs, key=lambda p: p[1]) if pairs else None

    def verdict(name: str, found: tuple[int, float] | None, need: float, above: bool) -> str:
        if found is None:
            return f"{name}: not measured (no batch size of the target in this run)"
        batch, value = found
        met = value >= need if above else value <= need
        by = value / need if above else need / value
        word = "met" if met else "MISSED"
        return f"{name}: {word}, worst {value:.2f} at B = {batch} ({by:.2f}x the bound {need:g})"

    f32 = [r for r in results if r["mode"] == "float32"]
    speedup = [(r["batch"], r["ratios"]["eigh/rotlearn"]) for r in f32]
    speedup = [(b, v) for b, v in speedup if v is not None]
    if device == "cpu":
        big = [(b, v) for b, v in speedup if b >= 16384]
        lines = [
            verdict("target 1, eigh/rotlearn >= 1 at every B", worst(speedup), 1.0, True),
            verdict("target 2, eigh/rotlearn >= 8 at B >= 16384", worst(big), 8.0, True),
            verdict("goal, eigh/rotlearn >= 10 at B >= 16384", worst(big), 10.0, True),
        ]
    else:
        at4096 = [(b, v) for b, v in speedup if b == 4096]
        sixd = [(r["batch"], r["ratios"]["rotlearn/sixd"]) for r in f32]
        sixd = [(b, v) for b, v in sixd if v is not None]
        lines = [
            verdict("GPU target, eigh/rotlearn >= 50 at B = 4096", worst(at4096), 50.0, True),
            verdict("GPU target, rotlearn/sixd <= 2 at every B", worst(sixd, False), 2.0, False),
        ]
    return lines


def _print_table(results: list[dict], names: list[str]) -> None:
    print("\nforward+backward, microseconds per sample (median over interleaved repeats)")
    header = f"{'mode':9s} {'B':>8s} " + " ".join(f"{n:>12s}" for n in names)
    print(header + " " + " ".join(f"{a[:5] + '/' + b[:3]:>10s}" for a, b in RATIOS))
    for res in results:
        medians = [res["rows"][n].get("median_us") for n in names]
        cells = " ".join(f"{m:12.4f}" if m is not None else f"{'err':>12s}" for m in medians)
        ratios = [res["ratios"][f"{a}/{b}"] for a, b in RATIOS]
        text = " ".join(f"{r:10.2f}" if r is not None else f"{'-':>10s}" for r in ratios)
        print(f"{res['mode']:9s} {res['batch']:8d} {cells} {text}")
    for res in results:
        for name, row in res["rows"].items():
            if "error" in row:
                print(f"  {res['mode']} B={res['batch']} {name}: {row['error']}")
    if roma is None:
        print("roma: not installed (`import roma` failed); its column is left out")


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--batches", default=None, help="default: " + str(BATCHES))
    parser.add_argument("--layers", default=None, help=f"subset of {','.join(LAYERS)}")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--budget", type=float, default=0.3, help="seconds per timed repeat")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    parser.add_argument(
        "--autocast", action="store_true", help="also bf16 autocast (default on CUDA)"
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch.cuda.is_available() is False on this machine")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    names = args.layers.split(",") if args.layers else list(LAYERS)
    unknown = [n for n in names if n not in LAYERS]
    if unknown:
        raise SystemExit(f"unknown layer(s) {unknown}; choose from {', '.join(LAYERS)}")
    modes = [("float32", False)]
    if args.autocast or device.type == "cuda":
        modes.append(("bf16-amp", True))
    path = resolve_kernel("auto", device)
    load_before = os.getloadavg()
    print(
        f"device {device}, threads {torch.get_num_threads()}, clock {args.clock}, rotlearn = "
        f"Jacobi on the {path} path, EIGH_BELOW {EIGH_BELOW}, load average {load_before}"
    )
    results = []
    batches = args.batches or BATCHES.get(device.type, BATCHES["cuda"])
    for mode, autocast in modes:
        for batch in [int(b) for b in batches.split(",")]:
            rows = bench_batch(batch, device, args, autocast, names)
            ratios = {f"{a}/{b}": _ratio(rows, a, b) for a, b in RATIOS}
            results.append({"mode": mode, "batch": batch, "rows": rows, "ratios": ratios})
            print(
                f"  {mode} B={batch}: "
                + ", ".join(
                    f"{n} {r['median_us']:.4f}" for n, r in rows.items() if "median_us" in r
                ),
                flush=True,
            )
    _print_table(results, names)
    verdicts = targets(results, device.type)
    print("\n".join(verdicts))
    info = machine(device) | {
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "clock": args.clock if device.type == "cpu" else "wall",
        "rotlearn_path": path,
        "EIGH_BELOW": EIGH_BELOW,
        "cuda": torch.version.cuda,
        "triton": _version("triton"),
        "roma": getattr(roma, "__version__", None),
        "repeats": args.repeats,
        "budget_s": args.budget,
        "targets": verdicts,
    }
    tag = f"{device.type}_{torch.get_num_threads()}t" if device.type == "cpu" else device.type
    out = write_json_atomic(
        args.out or RESULTS / f"a_layer_{tag}.json", {"machine": info, "results": results}
    )
    print(f"-> {out}")


if __name__ == "__main__":
    main()
