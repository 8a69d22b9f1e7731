"""Timing shared by the benchmark scripts."""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

# Source of `peak_rss()` for a benchmark's child process (`python -c PEAK_RSS + code`): its own
# peak resident memory in bytes. `ru_maxrss` would not do: a child started by subprocess carries
# its parent's peak over exec (a parent at 800 MiB makes any child report at least 800 MiB).
PEAK_RSS = """
def peak_rss():
    with open("/proc/self/status") as status:  # VmHWM: this process's own high-water mark
        return next(int(l.split()[1]) * 1024 for l in status if l.startswith("VmHWM:"))
"""


def median_seconds(fn: Callable[[], object], repeats: int = 5) -> float:
    """Median wall-clock seconds of `repeats` calls of `fn`, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo (Linux), else what `platform` knows."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def commit() -> str | None:
    """The git commit of the code measured (with "+" when the tree has changes), or None."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root, capture_output=True, text=True,
        )  # fmt: skip
    except OSError:
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+" if dirty.stdout.strip() else "")


def machine(device: object = "cpu") -> dict:
    """What a benchmark result must name: versions, CPU model, torch threads, GPU (if used),
    the code's commit."""
    import platform

    import torch

    device = torch.device(device)
    return {
        "commit": commit(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
    }
