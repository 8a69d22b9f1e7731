"""`rotlearn-predict CKPT INPUT [INPUT2]`: the rotation a trained model reads in an input, and
how sure.

Point models: INPUT is a point-cloud pair file, a `.npy` array (N, 6) or (B, N, 6), or a text
file of N lines "ux uy uz vx vy vz" (whitespace or commas; `#` starts a comment): the matched
pairs (u_i, v_i) with v_i = R u_i (a run on synthetic data reads unit u_i, as it trained on:
each pair is divided by |u_i| otherwise, with a note). Image-pair models (data=kitti,
data=mav): INPUT and INPUT2 are the two frames (e.g. sequences/00/image_2/000000.png and
000001.png), preprocessed as in training; the answer is C_21, the rotation from the first
camera to the second.

Per input (a set of N pairs, or an image pair) it prints:
  rotation     its angle and axis, and the quaternion (x, y, z, w);
  uncertainty  (heads with a belief: rep=a, rep=fisher) the radius of the belief's 90 % credible
               ball around the rotation, in degrees (`rotlearn.bingham.credible_radius_deg`;
               the belief calibrated as the checkpoint's calibration says, if any: tempered,
               and the ball of the mass its level map gives the 90 % level,
               `RotationEstimate.credible_mass`), from 4096 draws of the belief: two identical
               inputs may differ in the last digits, as the draws of each differ;
  OOD check    the DT score (paper eq. 26; lower = more confident), the threshold calibrated on
               the validation scores (`callbacks=ood`, beside the checkpoint) and the decision:
               keep when the score is below it, reject otherwise.
--json prints the same for scripts, with the rotation matrix R and the Bingham dispersion.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from rotlearn.errors import InputAdjustedWarning
from rotlearn.io import UnreadableFileError, read_number_array, read_number_rows
from rotlearn.paths import checkpoint_file

__all__ = ["describe", "main", "read_point_pairs", "text_lines"]


def read_point_pairs(path: str | Path, width: int = 6) -> np.ndarray:
    """Read a point-cloud pair file: (N, width) or (B, N, width) float64, all finite: a `.npy`
    array (`rotlearn.io.read_number_array`) or text rows (`rotlearn.io.read_number_rows`).

    Raises:
        FileNotFoundError: no such file; ValueError: naming the file and the line or row at fault.
    """
    path = Path(path)
    layout = "ux uy uz vx vy vz" if width == 6 else f"{width} numbers a row"
    if path.suffix in (".npy", ".npz"):
        return read_number_array(path, width, layout)
    if path.is_dir():
        raise ValueError(f"{path}: a folder; a point model reads one point-pair file")
    try:
        return read_number_rows(path, width, layout, commas=True)
    except UnreadableFileError as exc:  # not text: say what a point model reads
        raise UnreadableFileError(
            f"{exc}; a point model reads a .npy array (N, {width}) or (B, N, {width}) or text "
            f"rows '{layout}'"
        ) from None


def _read_input(predictor, paths: list[str], checkpoint: str):
    """The model's input from the command line's files: a point-pair file, or an image pair
    (read as the run's datamodule reads its frames; a checkpoint whose data config it refuses
    is named, in one line)."""
    if predictor.image_size is None:
        if len(paths) != 1:
            got = f"{len(paths)} input{'s' * (len(paths) != 1)}"
            raise ValueError(f"a point model reads one point-pair file, got {got}")
        return read_point_pairs(paths[0], predictor.in_channels or 6)
    if len(paths) != 2:
        got = f"{len(paths)} input{'s' * (len(paths) != 1)}"
        raise ValueError(f"an image-pair model reads two image files, got {got}")
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        datamodule = instantiate(predictor.config["data"])
    except InstantiationException as exc:  # what the constructor raised, with Hydra's words
        said = str(exc.__cause__ or exc).strip().splitlines() or [type(exc.__cause__).__name__]
        raise ValueError(f"{checkpoint}: its data config does not build: {said[0]}") from None
    return datamodule.read_pair(*paths)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rotlearn-predict",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "checkpoint",
        help="a run directory (the checkpoint its test scored: last.ckpt, or best.ckpt after "
        "test_ckpt=best) or a .ckpt file",
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
    from rotlearn.inference import load

    try:
        predictor = load(args.checkpoint, device=args.device)
        with warnings.catch_warnings(record=True) as notes:  # e.g. u_i scaled to unit length
            warnings.simplefilter("always", InputAdjustedWarning)
            estimate = predictor(_read_input(predictor, args.input, args.checkpoint))
    except (OSError, ValueError, TypeError, FloatingPointError) as exc:  # FP: a non-finite output
        print(f"rotlearn-predict: {exc}", file=sys.stderr)
        return 2
    for note in notes:  # rotlearn's changes to the input as notes; any other warning as it was
        if issubclass(note.category, InputAdjustedWarning):
            print(f"rotlearn-predict: note: {args.input[0]}: {note.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(note.message, note.category, note.filename, note.lineno)
    results = describe(estimate, getattr(predictor, "ood", None))
    if args.json:
        print(json.dumps(results if len(results) > 1 else results[0], indent=2))
        return 0
    head = getattr(getattr(predictor, "head", None), "name", None)
    for i, item in enumerate(results):
        if len(results) > 1:
            print(f"input {i}:")  # a set of N pairs, or an image pair
        print(text_lines(item, head))
    return 0


UNCERTAINTY_LEVEL = 0.9  # the mass of the credible ball whose radius rotlearn-predict prints


def describe(estimate: Any, ood: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Per pair of a `RotationEstimate`: the rotation (R, q_xyzw, angle_deg, axis), and where the
    head has a belief its uncertainty (the 90 % credible radius in degrees, the dispersion, the
    DT score, the temperature) and, given a calibrated threshold (`ood`), the OOD decision."""
    import torch  # here, not at the top: --help and a refused folder answer before torch loads

    q = estimate.q.double().cpu()
    sine = torch.linalg.vector_norm(q[:, :3], dim=-1)
    angles = torch.rad2deg(2.0 * torch.atan2(sine, q[:, 3].abs()))
    radii = None
    if estimate.A is not None:
        from rotlearn.bingham import credible_radius_deg

        generator = torch.Generator(device=estimate.A.device).manual_seed(0)  # same answer twice
        mass = max(float(estimate.credible_mass(UNCERTAINTY_LEVEL)), 1e-6)
        radii = credible_radius_deg(estimate.A, mass, generator=generator).cpu()
    results = []
    for i in range(estimate.R.shape[0]):
        axis = (q[i, :3] / sine[i]).tolist() if float(sine[i]) > 0 else [0.0, 0.0, 0.0]
        item: dict[str, Any] = {
            "R": estimate.R[i].tolist(),
            "q_xyzw": estimate.q[i].tolist(),
            "angle_deg": float(angles[i]),
            "axis": axis,
        }
        if radii is not None:
            item["uncertainty_deg"] = float(radii[i])
            item["uncertainty_level"] = UNCERTAINTY_LEVEL
        if estimate.dt is not None:
            item["dispersion"] = estimate.dispersion[i].tolist()
            item["dt_score"] = float(estimate.dt[i])
            item["temperature"] = estimate.temperature
        if estimate.keep is not None and ood is not None:
            item["ood"] = {"score": ood["score"], "value": item.get("dt_score"),
                           "threshold": float(ood["threshold"]), "q": float(ood["q"]),
                           "reference": ood.get("reference"),
                           "decision": "keep" if bool(estimate.keep[i]) else "reject"}  # fmt: skip
            item["keep"] = bool(estimate.keep[i])
        results.append(item)
    return results


def text_lines(item: dict[str, Any], head: str | None = None) -> str:
    """One pair of `describe` as the lines a person reads."""
    axis = ", ".join(f"{v:+.3f}" for v in item["axis"])
    q = ", ".join(f"{v:+.6f}" for v in item["q_xyzw"])
    lines = [
        f"  rotation     {item['angle_deg']:.3f} deg about ({axis})",
        f"  quaternion   (x, y, z, w) = ({q})",
    ]
    if "uncertainty_deg" in item:
        t = item.get("temperature", 1.0)
        tempered = f", temperature {t:.4g}" if t != 1 else ""
        lines.append(
            f"  uncertainty  {item['uncertainty_deg']:.3g} deg: "
            f"{100 * item['uncertainty_level']:.0f} % of the belief lies within it{tempered}"
        )
    else:
        lines.append(f"  uncertainty  none: rep={head} defines no belief (rep=a or rep=fisher do)")
    if "ood" in item:
        ood = item["ood"]
        side = "<" if ood["decision"] == "keep" else ">="
        scores = {"val": "validation", "train": "training"}.get(ood.get("reference"), "reference")
        lines.append(
            f"  OOD check    {ood['decision']}: {ood['score'].upper()} score {ood['value']:.4g} "
            f"{side} threshold {ood['threshold']:.4g} (the q = {ood['q']:g} quantile of the "
            f"{scores} scores; lower = more confident)"
        )
    elif "dt_score" in item:
        lines.append(
            f"  OOD check    no threshold with this checkpoint (train with callbacks=ood); "
            f"DT score {item['dt_score']:.4g} (lower = more confident)"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
