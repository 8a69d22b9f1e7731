"""The files an OOD evaluation leaves in its run directory: every sample's error and scores
(`ood_samples.csv`, read back by `read_samples`), the rejection table (`ood.csv`, and `ood.md`
built by `rotlearn.report.tables.ood_markdown`), and the calibrated threshold beside the run's
checkpoints. All written atomically (`rotlearn.io`); `rotlearn-report` draws its figures from
them."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from rotlearn.checkpoint import THRESHOLDS_FILE
from rotlearn.io import read_table, write_json_atomic, write_text_atomic

__all__ = ["SAMPLES_FILE", "read_samples", "write_samples", "write_tables", "write_thresholds"]

SAMPLES_FILE = "ood_samples.csv"


def write_samples(run_dir: str | os.PathLike, sets: Mapping[str, Mapping[str, Tensor]]) -> Path:
    """`ood_samples.csv` in `run_dir`: one row per scored sample, columns set, error (degrees),
    ood (1/0, empty for the unflagged train and noise sets) and one per score; atomically."""
    frames = []
    for name, data in sets.items():
        columns = {"set": name, "error": data["error"].numpy()}
        if "corrupted" in data:
            columns["ood"] = data["corrupted"].numpy().astype(int)
        for key, values in data.items():
            if key not in ("error", "corrupted"):
                columns[key] = values.numpy()
        frames.append(pd.DataFrame(columns))
    frame = pd.concat(frames, ignore_index=True)
    return write_text_atomic(Path(run_dir) / SAMPLES_FILE, frame.to_csv(index=False))


def read_samples(
    path: str | os.PathLike, root: str | os.PathLike | None = None
) -> dict[str, dict[str, Tensor]]:
    """The sets of `write_samples`' file, as `rotlearn.ood.evaluation.score_sets` returns them
    (float64 tensors, bool "corrupted" where flagged); `root`: the folder it must lie in (a run's).

    Raises:
        ValueError: naming the file, if it lacks the set or error column or leads out of `root`.
    """
    frame = read_table(path, root)  # bounded: a regular file of at most MAX_BYTES["CSV table"]
    if not {"set", "error"} <= set(frame.columns):
        raise ValueError(f"{path}: not an OOD samples file (needs the columns set and error)")
    sets = {}
    for name, part in frame.groupby("set", sort=False):
        data = {"error": torch.tensor(part["error"].to_numpy(dtype=np.float64))}
        if "ood" in part and part["ood"].notna().all():
            data["corrupted"] = torch.tensor(part["ood"].to_numpy(dtype=np.int64) != 0)
        for key in part.columns:
            if key not in ("set", "error", "ood"):
                data[key] = torch.tensor(part[key].to_numpy(dtype=np.float64))
        sets[str(name)] = data
    return sets


def write_tables(run_dir: str | os.PathLike, rep: str, frame: pd.DataFrame) -> Path:
    """`ood.csv` (every row of `frame`) and `ood.md` (`rotlearn.report.tables.ood_markdown`) in
    `run_dir`, atomically; returns the markdown's path."""
    from rotlearn.report.tables import ood_markdown

    run_dir = Path(run_dir)
    write_text_atomic(run_dir / "ood.csv", frame.to_csv(index=False))
    return write_text_atomic(run_dir / "ood.md", ood_markdown(rep, frame))


def write_thresholds(checkpoint_dir: str | os.PathLike, ood: Mapping[str, Any]) -> Path:
    """The calibrated threshold {"score", "threshold", "q"} and, where known, its "reference"
    set ("val" or "train") beside the checkpoints it belongs to
    (`rotlearn.checkpoint.THRESHOLDS_FILE`, read by `rotlearn.load`), atomically."""
    data = {"score": str(ood["score"]), "threshold": float(ood["threshold"]), "q": float(ood["q"])}
    if ood.get("reference") is not None:
        data["reference"] = str(ood["reference"])
    return write_json_atomic(Path(checkpoint_dir) / THRESHOLDS_FILE, data)
