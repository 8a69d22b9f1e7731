"""Speed of the Bingham belief (rotlearn.bingham): `python bench/bingham.py [--batches ...]`.

Microseconds per sample, median of --repeats timed calls after one warm-up, for
- logN:       log_normalizer(lam) without autograd (lam: (B, 3) dispersion coefficients);
- logN+grad:  log_normalizer(lam).sum().backward(), i.e. log N and d log N / d lam;
- nll+grad:   nll(A, q).mean().backward() from (B, 4, 4) matrices (includes eigvalsh);
- sample:     sample(A, 64) from (B / 64) matrices, per drawn quaternion;
for each batch size, dtype and torch thread count. The coefficients are spread log-uniformly over
[-1e4, -1e-3]. Prints a table and writes bench/results/bingham.json. Run it on an idle machine:
with other processes on the cores, 2 threads can be much slower than 1.
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

import torch

from rotlearn.bingham import log_normalizer, nll, sample
from rotlearn.io import write_json_atomic
from timing import median_seconds

RESULTS = Path(__file__).resolve().parent / "results"
DTYPES = {"float32": torch.float32, "float64": torch.float64}
TARGET_US = 2.0  # log N + gradient, float32, B = 131072 (issue "Bingham belief from A")


def _machine() -> dict:
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "load_average_1min_at_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


def _inputs(batch: int, dtype: torch.dtype, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    lam = -(10.0 ** (torch.rand(batch, 3, generator=gen, dtype=torch.float64) * 7 - 3))
    V = torch.linalg.qr(torch.randn(batch, 4, 4, generator=gen, dtype=torch.float64))[0]
    ev = torch.cat((torch.zeros(batch, 1, dtype=torch.float64), -lam.sort(-1).values.flip(-1)), -1)
    A = V @ torch.diag_embed(ev) @ V.mT
    q = torch.nn.functional.normalize(torch.randn(batch, 4, generator=gen, dtype=torch.float64))
    return lam.to(dtype), A.to(dtype), q.to(dtype)


def bench_one(batch: int, dtype: torch.dtype, repeats: int) -> dict:
    lam, A, q = _inputs(batch, dtype)

    def forward():
        with torch.no_grad():
            log_normalizer(lam)

    def forward_backward():
        x = lam.clone().requires_grad_(True)
        log_normalizer(x).sum().backward()

    def likelihood():
        a = A.clone().requires_grad_(True)
        nll(a, q).mean().backward()

    per_matrix = 64
    mats = A[: max(1, batch // per_matrix)]
    gen = torch.Generator().manual_seed(1)

    def draw():
        sample(mats, per_matrix, generator=gen)

    drawn = mats.shape[0] * per_matrix
    return {
        "logN_us": 1e6 * median_seconds(forward, repeats) / batch,
        "logN_grad_us": 1e6 * median_seconds(forward_backward, repeats) / batch,
        "nll_grad_us": 1e6 * median_seconds(likelihood, repeats) / batch,
        "sample_us": 1e6 * median_seconds(draw, repeats) / drawn,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--batches", default="1024,131072", help="comma-separated batch sizes")
    parser.add_argument("--dtypes", default="float32,float64", help="float32,float64")
    parser.add_argument(
        "--threads", default=f"1,{torch.get_num_threads()}", help="torch thread counts to try"
    )
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, default=RESULTS / "bingham.json")
    args = parser.parse_args(argv)
    batches = [int(b) for b in args.batches.split(",")]
    dtypes = args.dtypes.split(",")
    unknown = set(dtypes) - set(DTYPES)
    if unknown:
        parser.error(f"unknown dtype(s) {sorted(unknown)}; choose from {sorted(DTYPES)}")
    threads = sorted({int(t) for t in args.threads.split(",")})
    machine = _machine()
    rows = []
    for n_threads in threads:
        torch.set_num_threads(n_threads)
        for batch in batches:
            for name in dtypes:
                row = {"threads": n_threads, "batch": batch, "dtype": name}
                row |= bench_one(batch, DTYPES[name], args.repeats)
                rows.append(row)
                print(".", end="", flush=True)
    print(f"\nBingham belief, microseconds per sample (median of {args.repeats})")
    header = f"{'threads':>7s} {'batch':>7s} {'dtype':>8s} {'logN':>8s} {'logN+grad':>10s}"
    print(f"{header} {'nll+grad':>9s} {'sample':>8s}")
    for r in rows:
        print(
            f"{r['threads']:7d} {r['batch']:7d} {r['dtype']:>8s} {r['logN_us']:8.3f} "
            f"{r['logN_grad_us']:10.3f} {r['nll_grad_us']:9.3f} {r['sample_us']:8.3f}"
        )
    target = [r for r in rows if r["dtype"] == "float32" and r["batch"] == 131072]
    if target:
        print(f"target: log N + gradient, float32, B=131072, <= {TARGET_US} us per sample:")
    for r in target:
        us = r["logN_grad_us"]
        verdict = "met" if us <= TARGET_US else f"missed by {us / TARGET_US:.2f}x"
        print(f"  {r['threads']} thread(s): {us:.3f} us, {verdict}")
    result = {"machine": machine, "target_us": TARGET_US, "rows": rows}
    path = write_json_atomic(args.out, {"result": result})
    shown = path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path
    print(f"-> {shown}")


if __name__ == "__main__":
    main()
