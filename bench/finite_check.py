"""Cost of the NaN/inf check of training steps: `python bench/finite_check.py [--device cuda]`.

Milliseconds per training step (forward, loss, backward, Adam step) of the paper's synthetic
setting (PointNet, batch 100, 100 matches; `--rep`, A by default), the step driven by hand (no
Lightning loop, so that only the check differs; `training_step` with its metric updates), median
over --repeats runs of --steps steps, the modes interleaved:
- none:          no check at all (the floor);
- sync:          the former check, `bool(torch.isfinite(t).all())` on the network output and the
                 loss: two host syncs per step;
- device/1:      rotlearn.lit.finite (device record, gradients zeroed after a failure) read every
                 step (`model.finite_check_every=1`: one host sync per step);
- device/N:      the same read every N steps (N = `FINITE_CHECK_EVERY`, the default).
Prints a table and writes bench/results/finite_check.json. On a CPU a host sync costs nothing
(the ops are done when they return), so there it measures only the check's extra ops; the syncs
matter on a GPU, where the host would otherwise run ahead of the device.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from rotlearn.cli.train import build
from rotlearn.config import compose
from rotlearn.io import write_json_atomic
from rotlearn.lit.finite import FINITE_CHECK_EVERY

RESULTS = Path(__file__).resolve().parent / "results"
MODES = ("none", "sync", "device/1", f"device/{FINITE_CHECK_EVERY}")


def _model_and_batch(rep: str, device: torch.device, tmp: Path, overrides: list[str]):
    model, datamodule, _ = build(compose([f"rep={rep}", "logger=none", *overrides], output_dir=tmp))
    model = model.to(device)
    batch = datamodule.draw(0, 0, datamodule.batch_size, device)
    return model, batch


def _sync_check(name, value, stage, batch_idx, inputs_bad) -> None:
    if not bool(torch.isfinite(value).all()):  # the former check: a host sync
        raise FloatingPointError(name)


def _set_mode(model, mode: str) -> int:
    """Install `mode`'s check on `model`; returns its read interval (0: no deferred reads)."""
    for name in ("_observe", "_inputs_bad"):
        model.__dict__.pop(name, None)  # back to the class's (device) check
    if mode == "none":
        model._observe, model._inputs_bad = (lambda *args: None), (lambda batch: None)
    elif mode == "sync":
        model._observe, model._inputs_bad = _sync_check, (lambda batch: None)
    return int(mode.split("/")[1]) if mode.startswith("device") else 0


def _steps(model, batch, optimizer, mode: str, steps: int) -> None:
    """`steps` training steps as Lightning runs them (training_step with its metric updates,
    backward, the hook before the optimizer step, the step), with `mode`'s check."""
    every = _set_mode(model, mode)
    for i in range(steps):
        optimizer.zero_grad(set_to_none=True)
        loss = model.training_step(batch, i)
        loss.backward()
        model.on_before_optimizer_step(optimizer)
        optimizer.step()
        if every and (i + 1) % every == 0:
            model._read_finite()
    if every:
        model._read_finite()
    model.train_err.reset()  # the epoch's metrics, so that runs do not grow them
    model.train_loss.reset()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--rep", default="a")
    parser.add_argument("--steps", type=int, default=2 * FINITE_CHECK_EVERY)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. net.hidden=...")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with tempfile.TemporaryDirectory() as tmp:
        model, batch = _model_and_batch(args.rep, device, Path(tmp), args.overrides)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    times: dict[str, list[float]] = {mode: [] for mode in MODES}
    for mode in MODES:
        _steps(model, batch, optimizer, mode, 5)  # warm-up
    for _ in range(args.repeats):  # the modes interleaved, so that a drift hits each alike
        for mode in MODES:
            sync()
            start = time.perf_counter()
            _steps(model, batch, optimizer, mode, args.steps)
            sync()
            times[mode].append((time.perf_counter() - start) / args.steps * 1e3)
    rows = {m: {"ms_per_step": statistics.median(t), "all_ms": t} for m, t in times.items()}
    floor = rows["none"]["ms_per_step"]
    setting = f"{device}, rep={args.rep}, {' '.join(args.overrides) or 'paper setting'}"
    print(f"{'mode':<12} {'ms/step':>9} {'vs none':>8}   ({setting})")
    for mode, row in rows.items():
        print(f"{mode:<12} {row['ms_per_step']:9.3f} {row['ms_per_step'] / floor:8.3f}")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor()
    RESULTS.mkdir(exist_ok=True)
    write_json_atomic(
        RESULTS / f"finite_check_{device.type}.json",
        {
            "device": name or platform.machine(),
            "torch": torch.__version__,
            "threads": args.threads,
            "rep": args.rep,
            "overrides": args.overrides,
            "steps": args.steps,
            "repeats": args.repeats,
            "results": rows,
        },
    )


if __name__ == "__main__":
    main()
