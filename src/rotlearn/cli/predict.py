"""`rotlearn-predict CKPT INPUT [INPUT2]`: the rotation a trained model reads in an input, and
how sure.

Point models: INPUT is a point-cloud pair file, a `.npy` array (N, 6) or (B, N, 6), or a text
file of N lines "ux uy uz vx vy vz" (whitespace or commas; `#` starts a comment): the matched
pairs (u_i, v_i) with v_i = R u_i. Image-pair models (data=kitti, data=mav): INPUT and INPUT2 are
the two frames (e.g. sequences/00/image_2/000000.png and 000001.png), preprocessed as in
training; the answer is C_21, the rotation from the first camera to the second. The uncertainty
(A head) is that of the belief tempered by the checkpoint's calibrated temperature, if any.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from rotlearn.io import read_number_rows
from rotlearn.paths import checkpoint_file

__all__ = ["main", "read_point_pairs"]


def read_point_pairs(path: str | Path, width: int = 6) -> np.ndarray:
    """Read a point-cloud pair file: (N, width) or (B, N, width) float64.

    Raises:
        ValueError: naming the file and line of the first malformed row.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no input file at {path}")
    if path.suffix == ".npy":
        array = np.load(path, allow_pickle=False)
        if array.ndim not in (2, 3) or array.shape[-1] != width:
            expected = f"(N, {width}) or (B, N, {width})"
            raise ValueError(f"{path}: expected an array of shape {expected}, got {array.shape}")
        return array.astype(np.float64)
    return read_number_rows(path, width, "ux uy uz vx vy vz", commas=True)


def _read_input(predictor, paths: list[str]):
    """The model's input from the command line's files: a point-pair file, or an image pair."""
    if predictor.image_size is None:
        if len(paths) != 1:
            raise ValueError(f"a point model reads one point-pair file, got {len(paths)} inputs")
        return read_point_pairs(paths[0], predictor.in_channels or 6)
    if len(paths) != 2:
        raise ValueError(f"an image-pair model reads two image files, got {len(paths)} inputs")
    from hydra.utils import instantiate

    datamodule = instantiate(predictor.config["data"])
    return datamodule.read_pair(*paths)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rotlearn-predict",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "checkpoint", help="a run directory (its checkpoints/last.ckpt) or a .ckpt file"
    )
    parser.add_argument(
        "input",
        nargs="+",
        help="a point-pair file (.npy (N, 6) or (B, N, 6), or text rows 'ux uy uz vx vy vz'), "
        "or the two image files of an image-pair model",
    )
    parser.add_argument(
        "--device", default="cpu", help="where the model runs: cpu (default), cuda, cuda:1, ..."
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    args = parser.parse_args(argv)
    try:  # a folder that is no run (or a sweep: its jobs named) is refused before torch loads
        checkpoint_file(args.checkpoint)
    except FileNotFoundError as exc:
        print(f"rotlearn-predict: {exc}", file=sys.stderr)
        return 2

    import torch

    from rotlearn.geometry import angle_deg
    from rotlearn.inference import load

    try:
        predictor = load(args.checkpoint, device=args.device)
        estimate = predictor(_read_input(predictor, args.input))
    except (OSError, ValueError, TypeError) as exc:
        print(f"rotlearn-predict: {exc}", file=sys.stderr)
        return 2
    identity = torch.eye(3, dtype=estimate.R.dtype)
    results = []
    for i in range(estimate.R.shape[0]):
        item = {
            "R": estimate.R[i].tolist(),
            "q_xyzw": estimate.q[i].tolist(),
            "angle_deg": float(angle_deg(estimate.R[i].cpu(), identity)),
        }
        if estimate.dt is not None:
            item["dispersion"] = estimate.dispersion[i].tolist()
            item["dt_score"] = float(estimate.dt[i])
            item["temperature"] = estimate.temperature
        if estimate.keep is not None:
            item["keep"] = bool(estimate.keep[i])
        results.append(item)
    if args.json:
        print(json.dumps(results if len(results) > 1 else results[0], indent=2))
        return 0
    for i, item in enumerate(results):
        prefix = f"[{i}] " if len(results) > 1 else ""
        print(f"{prefix}rotation angle {item['angle_deg']:.4f} deg")
        print(f"{prefix}q (x, y, z, w) = " + " ".join(f"{v:+.6f}" for v in item["q_xyzw"]))
        for row in item["R"]:
            print(f"{prefix}  " + " ".join(f"{v:+.6f}" for v in row))
        if "dt_score" in item:
            disp = ", ".join(f"{v:.4g}" for v in item["dispersion"])
            t = item["temperature"]
            tempered = f", temperature {t:.4g}" if t != 1 else ""
            print(
                f"{prefix}uncertainty: DT score {item['dt_score']:.4g} (lower = more confident), "
                f"Bingham dispersion ({disp}){tempered}"
            )
        if "keep" in item:
            print(f"{prefix}OOD check: {'keep' if item['keep'] else 'reject'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
