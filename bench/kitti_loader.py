"""KITTI loader throughput (issue 5): first-time preprocessing rate, then cached pairs per second
served to a training loop by 2 loader workers (batch 32, 224 x 224 frames): as the loader yields
them (uint8), and finished as the model sees them (`finish_batch`: erasing, floats, normalisation).

Uses the KITTI-format demo data (written to a temporary directory). `make bench ARGS=kitti_loader`.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from rotlearn.data import KittiOdometryDataModule
from rotlearn.data.demo.kitti import write_kitti_demo
from rotlearn.io import write_json_atomic

RESULTS = Path(__file__).resolve().parent / "results"
TARGET_PAIRS_PER_S = 1000


def measure(root: Path, workers: int, epochs: int, batch_size: int) -> dict:
    sequences = sorted(p.name for p in (root / "sequences").iterdir())
    frames = sum(len(list((root / "sequences" / s / "image_2").glob("*.png"))) for s in sequences)

    def module() -> KittiOdometryDataModule:
        return KittiOdometryDataModule(
            str(root),
            train_sequences=sequences[1:],
            test_sequences=sequences[:1],
            batch_size=batch_size,
            num_workers=workers,
        )

    start = time.perf_counter()
    module().setup()  # decodes, resizes and caches every frame
    preprocess_s = time.perf_counter() - start

    dm = module()
    dm.setup()
    loader = dm.train_dataloader()
    rates = {}
    for name, convert in (("uint8", False), ("float", True)):
        iterator = iter(loader)
        next(iterator)  # the workers have started
        served, start = 0, time.perf_counter()
        for epoch in range(epochs):
            for batch in iterator if epoch == 0 else iter(loader):
                x = dm.finish_batch(batch)["input"] if convert else batch["input"]
                served += x.shape[0]
        rates[name] = served / (time.perf_counter() - start)
    return {
        "frames": frames,
        "preprocess_frames_per_s": frames / preprocess_s,
        "pairs_per_s": rates["uint8"],
        "pairs_per_s_with_float_conversion": rates["float"],
        "workers": workers,
        "batch_size": batch_size,
        "image_size": dm.image_size,
        "target_pairs_per_s": TARGET_PAIRS_PER_S,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=32)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = write_kitti_demo(tmp)
        result = measure(root, args.workers, args.epochs, args.batch_size)
    print(
        f"\nKITTI loader ({result['frames']} demo frames -> {result['image_size']}^2, "
        f"{result['workers']} workers, batch {result['batch_size']})"
    )
    print(f"  first-time preprocessing: {result['preprocess_frames_per_s']:8.1f} frames/s")
    print(
        f"  cached pairs served:      {result['pairs_per_s']:8.1f} pairs/s (uint8, as the loader "
        f"yields them; target >= {TARGET_PAIRS_PER_S})"
    )
    print(
        f"  ... and made float:       {result['pairs_per_s_with_float_conversion']:8.1f} pairs/s "
        "(with the datamodule's conversion after the transfer, on this CPU)"
    )
    path = write_json_atomic(RESULTS / "kitti_loader.json", result)
    print(f"-> {path}")
    return json.loads(path.read_text())


if __name__ == "__main__":
    main()
