"""Cost of the rotation representation layers: microseconds per sample, forward and backward.

Layers (each on random inputs of its own shape):
- eigen4: rotlearn.geometry.eigen4.sym4_eigh_min on (B, 4, 4) symmetric A (check=False), outputs
  the 4 eigenvalues and the canonical minimum eigenvector q;
- eigh: the same outputs from torch.linalg.eigh (eigenvalues, quat_canonical(V[..., 0]));
- sixd: rotlearn.geometry.sixd_to_rotmat on (B, 6);
- quat: rotlearn.geometry.quat_normalize on (B, 4);
- svd9d: rotlearn.geometry.special_orthogonalize on (B, 3, 3).
The backward pass is that of a random linear function of every output (autograd.grad).

Then a head-only training step (nn.Linear(64, out_dim), batch 4096, Adam, chordal loss
|R - R*|_F^2) for rep=a with eigen4 (and with eigh, as the A head does today) against sixd.

Every number is the median over repeated timings; the spread (max - min) / median of the repeats
is printed beside it, and the load average before and after the run goes into the JSON, because
another process may share the machine. Ratios are computed within the run.

    .venv/bin/python bench/rep_layers.py                 # CPU, about 3 minutes
    .venv/bin/python bench/rep_layers.py --device cuda
    .venv/bin/python bench/rep_layers.py --batches 16384 --dtypes float32 --threads 1
    .venv/bin/python bench/rep_layers.py --crossover     # jacobi vs eigh: where `auto` switches

`--crossover` times `sym4_eigh_min(method="jacobi")` against `method="eigh"` on the eager path
(`kernel="eager"`: where a fused kernel runs, "auto" is always jacobi; forward and
forward+backward, float32, batch sizes 1 ... 65536) and reports the smallest batch from which
jacobi's forward+backward is faster at that and every larger size measured: the value for
`rotlearn.geometry.eigen4.EIGH_BELOW` on this machine. Written to
bench/results/solver_crossover[_<device>].json.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn

from rotlearn.geometry import (
    a_from_vec,
    chordal_distance_sq,
    quat_canonical,
    quat_normalize,
    quat_to_rotmat,
    sixd_to_rotmat,
    special_orthogonalize,
)
from rotlearn.geometry.eigen4 import sym4_eigh_min
from rotlearn.io import write_json_atomic

RESULTS = Path(__file__).resolve().parent / "results"
DTYPES = {"float32": torch.float32, "float64": torch.float64}


# ---------------------------------------------------------------------------------------------
# the layers: name -> (input shape per sample, function returning a tuple of outputs)
# ---------------------------------------------------------------------------------------------


def _eigen4(A: Tensor) -> tuple[Tensor, ...]:
    return sym4_eigh_min(A, check=False)


def _eigh(A: Tensor) -> tuple[Tensor, ...]:
    eigenvalues, vectors = torch.linalg.eigh(A)
    return eigenvalues, quat_canonical(vectors[..., 0])


LAYERS: dict[str, tuple[tuple[int, ...], Callable[[Tensor], tuple[Tensor, ...]]]] = {
    "eigen4": ((4, 4), _eigen4),
    "eigh": ((4, 4), _eigh),
    "sixd": ((6,), lambda x: (sixd_to_rotmat(x),)),
    "quat": ((4,), lambda x: (quat_normalize(x),)),
    "svd9d": ((3, 3), lambda x: (special_orthogonalize(x),)),
}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timeit(fn: Callable[[], object], device: torch.device, budget_s: float) -> dict:
    """Median seconds per call over repeats sized to `budget_s` in all; also the spread."""
    fn()  # warm-up (allocator, lazy init)
    _sync(device)
    start = time.perf_counter()
    fn()
    _sync(device)
    single = max(time.perf_counter() - start, 1e-7)
    repeats = 7 if single * 7 <= budget_s else max(3, int(budget_s / single))
    inner = max(1, int(budget_s / (repeats * single)))
    times = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        for _ in range(inner):
            fn()
        _sync(device)
        times.append((time.perf_counter() - start) / inner)
    median = statistics.median(times)
    return {
        "median_s": median,
        "min_s": min(times),
        "spread": (max(times) - min(times)) / median,
        "repeats": repeats,
        "inner": inner,
    }


def _inputs(name: str, batch: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    shape, _ = LAYERS[name]
    gen = torch.Generator(device=device).manual_seed(0)
    x = torch.randn((batch, *shape), generator=gen, dtype=dtype, device=device)
    if name in ("eigen4", "eigh"):
        x = (x + x.transpose(-1, -2)) / 2
    return x


def bench_layers(
    batches: list[int], dtypes: list[str], device: torch.device, budget_s: float
) -> list[dict]:
    rows = []
    for dtype_name in dtypes:
        dtype = DTYPES[dtype_name]
        for batch in batches:
            for name, (_, layer) in LAYERS.items():
                x = _inputs(name, batch, dtype, device)
                with torch.no_grad():
                    weights = [torch.randn_like(out) for out in layer(x)]
                leaf = x.clone().requires_grad_(True)

                def forward(layer=layer, x=x):
                    with torch.no_grad():
                        return layer(x)

                def forward_backward(layer=layer, leaf=leaf, weights=weights):
                    outs = layer(leaf)
                    loss = sum((o * w).sum() for o, w in zip(outs, weights, strict=True))
                    return torch.autograd.grad(loss, leaf)

                fwd = _timeit(forward, device, budget_s)
                fwdbwd = _timeit(forward_backward, device, budget_s)
                rows.append(
                    {
                        "layer": name,
                        "dtype": dtype_name,
                        "batch": batch,
                        "forward_us": 1e6 * fwd["median_s"] / batch,
                        "forward_backward_us": 1e6 * fwdbwd["median_s"] / batch,
                        "forward_spread": fwd["spread"],
                        "forward_backward_spread": fwdbwd["spread"],
                        "repeats": [fwd["repeats"], fwdbwd["repeats"]],
                    }
                )
                row = rows[-1]
                print(
                    f"  {dtype_name} B={batch:<6d} {name:7s} fwd {row['forward_us']:9.4f} us"
                    f" (+-{50 * fwd['spread']:3.0f}%)  fwd+bwd {row['forward_backward_us']:9.4f}"
                    f" us (+-{50 * fwdbwd['spread']:3.0f}%)",
                    flush=True,
                )
    return rows


def _ratios(rows: list[dict]) -> list[dict]:
    """eigh / eigen4 (speed-up) and eigen4 / sixd (cost vs 6D), per dtype, batch and pass."""
    index = {(r["layer"], r["dtype"], r["batch"]): r for r in rows}
    out = []
    for (layer, dtype, batch), row in index.items():
        if layer != "eigen4":
            continue
        eigh, sixd = index[("eigh", dtype, batch)], index[("sixd", dtype, batch)]
        entry = {"dtype": dtype, "batch": batch}
        for key in ("forward_us", "forward_backward_us"):
            entry[f"eigh_over_eigen4_{key[:-3]}"] = eigh[key] / row[key]
            entry[f"eigen4_over_sixd_{key[:-3]}"] = row[key] / sixd[key]
        out.append(entry)
    return out


# ---------------------------------------------------------------------------------------------
# head-only training step
# ---------------------------------------------------------------------------------------------


def _rotation_eigen4(raw: Tensor) -> Tensor:
    _, q = sym4_eigh_min(a_from_vec(raw), check=False)
    return quat_to_rotmat(q)


def _rotation_eigh(raw: Tensor) -> Tensor:
    _, q = _eigh(a_from_vec(raw))
    return quat_to_rotmat(q)


HEADS: dict[str, tuple[int, Callable[[Tensor], Tensor]]] = {
    "a_eigen4": (10, _rotation_eigen4),
    "a_eigh": (10, _rotation_eigh),
    "sixd": (6, sixd_to_rotmat),
}


def bench_training_step(device: torch.device, budget_s: float, batch: int = 4096) -> dict:
    gen = torch.Generator(device=device).manual_seed(1)
    features = torch.randn(batch, 64, generator=gen, device=device)
    target = quat_to_rotmat(quat_normalize(torch.randn(batch, 4, generator=gen, device=device)))
    rows = {}
    for name, (out_dim, to_rotation) in HEADS.items():
        torch.manual_seed(0)
        net = nn.Linear(64, out_dim).to(device)
        optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)

        def step(net=net, optimiser=optimiser, to_rotation=to_rotation):
            optimiser.zero_grad(set_to_none=True)
            loss = chordal_distance_sq(to_rotation(net(features)), target).mean()
            loss.backward()
            optimiser.step()

        timing = _timeit(step, device, 2 * budget_s)
        rows[name] = {"step_ms": 1e3 * timing["median_s"], "spread": timing["spread"]}
        print(
            f"  train step {name:9s} {rows[name]['step_ms']:8.3f} ms"
            f" (+-{100 * timing['spread'] / 2:3.0f}%)",
            flush=True,
        )
    sixd = rows["sixd"]["step_ms"]
    return {
        "batch": batch,
        "steps": rows,
        "a_eigen4_over_sixd": rows["a_eigen4"]["step_ms"] / sixd,
        "a_eigh_over_sixd": rows["a_eigh"]["step_ms"] / sixd,
    }


# ---------------------------------------------------------------------------------------------


def _print_table(rows: list[dict], ratios: list[dict]) -> None:
    layers = list(LAYERS)
    for key, title in (("forward_us", "forward"), ("forward_backward_us", "forward+backward")):
        print(f"\n{title}: microseconds per sample (median)")
        print(f"{'dtype':8s} {'B':>7s} " + " ".join(f"{n:>9s}" for n in layers))
        for dtype in dict.fromkeys(r["dtype"] for r in rows):
            for batch in dict.fromkeys(r["batch"] for r in rows):
                cells = {
                    r["layer"]: r[key] for r in rows if (r["dtype"], r["batch"]) == (dtype, batch)
                }
                print(f"{dtype:8s} {batch:7d} " + " ".join(f"{cells[n]:9.4f}" for n in layers))
    print("\nratios: eigh/eigen4 (speed-up of the new solver), eigen4/sixd (cost relative to 6D)")
    print(f"{'dtype':8s} {'B':>7s} {'fwd':>7s} {'f+b':>7s} | {'fwd':>7s} {'f+b':>7s}")
    for r in ratios:
        print(
            f"{r['dtype']:8s} {r['batch']:7d} {r['eigh_over_eigen4_forward']:7.2f} "
            f"{r['eigh_over_eigen4_forward_backward']:7.2f} | "
            f"{r['eigen4_over_sixd_forward']:7.2f} {r['eigen4_over_sixd_forward_backward']:7.2f}"
        )


def _machine(device: torch.device, load_before, load_after) -> dict:
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "device": str(device),
        "load_average_before": load_before,
        "load_average_after": load_after,
    }


CROSSOVER_BATCHES = "1,8,32,100,256,512,1024,2048,4096,8192,16384,65536"


def bench_crossover(batches: list[int], dtype: torch.dtype, device: torch.device, budget_s: float):
    """jacobi vs eigh forward of `sym4_eigh_min` (same backward) per batch size; the crossover."""
    rows = []
    for batch in batches:
        A = _inputs("eigen4", batch, dtype, device)
        leaf = A.clone().requires_grad_(True)
        row: dict = {"batch": batch}
        for method in ("jacobi", "eigh"):
            with torch.no_grad():
                weights = [torch.randn_like(o) for o in sym4_eigh_min(A, check=False)]

            def forward(method=method, A=A):
                with torch.no_grad():
                    return sym4_eigh_min(A, check=False, method=method, kernel="eager")

            def forward_backward(method=method, weights=weights, leaf=leaf):
                outs = sym4_eigh_min(leaf, check=False, method=method, kernel="eager")
                loss = sum((o * w).sum() for o, w in zip(outs, weights, strict=True))
                return torch.autograd.grad(loss, leaf)

            row[f"{method}_forward_ms"] = 1e3 * _timeit(forward, device, budget_s)["median_s"]
            row[f"{method}_forward_backward_ms"] = (
                1e3 * _timeit(forward_backward, device, budget_s)["median_s"]
            )
        row["jacobi_faster"] = row["jacobi_forward_backward_ms"] < row["eigh_forward_backward_ms"]
        rows.append(row)
        print(
            f"  B={batch:<6d} fwd+bwd ms: jacobi {row['jacobi_forward_backward_ms']:9.3f}"
            f"  eigh {row['eigh_forward_backward_ms']:9.3f}   fwd ms: jacobi"
            f" {row['jacobi_forward_ms']:9.3f}  eigh {row['eigh_forward_ms']:9.3f}",
            flush=True,
        )
    crossover = None  # smallest measured batch from which jacobi wins at every larger one
    for row in reversed(rows):
        if not row["jacobi_faster"]:
            break
        crossover = row["batch"]
    return rows, crossover


def main_crossover(args: argparse.Namespace, device: torch.device) -> None:
    batches = [int(b) for b in (args.batches or CROSSOVER_BATCHES).split(",")]
    dtype = DTYPES[args.dtypes.split(",")[0]]
    load_before = os.getloadavg()
    print(f"device {device}, threads {torch.get_num_threads()}, load average {load_before}")
    rows, crossover = bench_crossover(batches, dtype, device, args.budget)
    print(
        f"\ncrossover: jacobi's forward+backward is faster from B = {crossover} on"
        if crossover is not None
        else "\ncrossover: eigh is faster (or level) at every batch size measured"
    )
    from rotlearn.geometry.eigen4 import EIGH_BELOW

    name = device.type.replace(":", "_")
    result = {
        "machine": _machine(device, load_before, os.getloadavg()),
        "dtype": str(dtype).removeprefix("torch."),
        "rows": rows,
        "crossover_batch": crossover,
        "EIGH_BELOW": EIGH_BELOW,
    }
    out = args.out if args.out != RESULTS / "rep_layers.json" else None
    path = write_json_atomic(out or RESULTS / f"solver_crossover_{name}.json", result)
    print(f"-> {path}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--dtypes", default="float32,float64")
    parser.add_argument("--batches", default=None, help="default 1,64,1024,16384,131072")
    parser.add_argument(
        "--crossover", action="store_true", help="jacobi vs eigh per batch size (EIGH_BELOW)"
    )
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    parser.add_argument(
        "--budget", type=float, default=0.6, help="seconds of timing per measurement (approx.)"
    )
    parser.add_argument("--no-train", action="store_true", help="skip the training-step bench")
    parser.add_argument("--out", type=Path, default=RESULTS / "rep_layers.json")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if args.crossover:
        main_crossover(args, device)
        return
    batches = [int(b) for b in (args.batches or "1,64,1024,16384,131072").split(",")]
    dtypes = args.dtypes.split(",")
    load_before = os.getloadavg()
    started = time.perf_counter()
    print(f"device {device}, threads {torch.get_num_threads()}, load average {load_before}")
    rows = bench_layers(batches, dtypes, device, args.budget)
    ratios = _ratios(rows)
    training = None if args.no_train else bench_training_step(device, args.budget)
    _print_table(rows, ratios)
    if training is not None:
        print(
            f"\nhead-only training step (batch {training['batch']}): "
            + ", ".join(f"{k} {v['step_ms']:.3f} ms" for k, v in training["steps"].items())
            + f"; a_eigen4/sixd = {training['a_eigen4_over_sixd']:.2f}, "
            f"a_eigh/sixd = {training['a_eigh_over_sixd']:.2f}"
        )
    spreads = [r[k] for r in rows for k in ("forward_spread", "forward_backward_spread")]
    elapsed = time.perf_counter() - started
    load_after = os.getloadavg()
    print(
        f"\nnoise: spread (max-min)/median of the repeats: median {statistics.median(spreads):.2f},"
        f" max {max(spreads):.2f}; load average before {load_before[0]:.2f}, after"
        f" {load_after[0]:.2f}; {elapsed:.0f} s"
    )
    result = {
        "machine": _machine(device, load_before, load_after),
        "layers": rows,
        "ratios": ratios,
        "training_step": training,
        "elapsed_s": elapsed,
    }
    path = write_json_atomic(args.out, result)
    print(f"-> {path}")


if __name__ == "__main__":
    main()
