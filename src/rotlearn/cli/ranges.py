"""The value ranges rotlearn adds to what the constructors' signatures say (`cli.signatures`).

Each rule maps a value to None (fine) or to what is wrong with it, for the config message
`config key <key>: <what>`. One table per kind of component: `OPTIM_RANGES`, `TRAINER_RANGES`,
`SCHEDULER_RANGES`, `NET_RANGES`, `CHECKPOINT_RANGES`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

__all__ = [
    "CHECKPOINT_RANGES",
    "NET_RANGES",
    "OPTIM_RANGES",
    "SCHEDULER_RANGES",
    "TRAINER_RANGES",
    "non_negative",
    "non_negative_int",
    "optional",
    "positive",
    "positive_int",
]


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def positive(v: Any) -> str | None:
    return None if _number(v) and v > 0 else "must be a positive number"


def non_negative(v: Any) -> str | None:
    return None if _number(v) and v >= 0 else "must be a number >= 0"


def positive_int(v: Any) -> str | None:
    return None if _integer(v) and v > 0 else "must be a positive integer"


def non_negative_int(v: Any) -> str | None:
    return None if _integer(v) and v >= 0 else "must be an integer >= 0"


def optional(check: Callable[[Any], str | None]) -> Callable[[Any], str | None]:
    def checked(v: Any) -> str | None:
        message = check(v)
        return message and f"{message} or null"

    return lambda v: None if v is None else checked(v)


def _betas(v: Any) -> str | None:
    ok = isinstance(v, (list, tuple)) and all(_number(b) and 0 <= b < 1 for b in v)
    return None if ok else "must be a list of numbers in [0, 1)"


def _max_epochs(v: Any) -> str | None:
    if _integer(v) and v > 0:
        return None
    if v in (-1, 0) and _integer(v):
        return (
            "must be a positive integer (Lightning reads -1 as 'train forever', 0 as no training)"
        )
    return "must be a positive integer"


def _devices(v: Any) -> str | None:
    if _integer(v) and (v > 0 or v == -1):
        return None
    if isinstance(v, str) and (
        v == "auto" or all(p.strip().lstrip("-").isdigit() for p in v.split(","))
    ):
        return None
    if isinstance(v, (list, tuple)) and v and all(_integer(d) and d >= 0 for d in v):
        return None
    return "must be a positive integer, -1 (every device), 'auto', or a list of device indices"


def _batches(v: Any) -> str | None:
    ok = v is None or (_integer(v) and v >= 0) or (isinstance(v, float) and 0 <= v <= 1)
    return None if ok else "must be an integer >= 0, a fraction in [0, 1], or null"


def _one_of(*choices: Any) -> Callable[[Any], str | None]:
    return lambda v: None if v in choices else f"must be one of {', '.join(map(str, choices))}"


def _registered(kind: str, names: Callable[[], Iterable[str]]) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if not isinstance(v, str):
            return None  # a _target_ mapping: checked by its constructor
        allowed = sorted({"auto", *names()})
        return None if v in allowed else f"must be a {kind} Lightning knows: {', '.join(allowed)}"

    return check


def _accelerators() -> Iterable[str]:
    from lightning.pytorch.accelerators import AcceleratorRegistry

    return [*AcceleratorRegistry.available_accelerators(), "gpu"]


def _strategies() -> Iterable[str]:
    from lightning.pytorch.strategies import StrategyRegistry

    return StrategyRegistry.available_strategies()


OPTIM_RANGES = {
    "lr": positive,
    "weight_decay": non_negative,
    "eps": non_negative,
    "momentum": non_negative,
    "betas": _betas,
}
TRAINER_RANGES = {
    "max_epochs": _max_epochs,
    "min_epochs": optional(non_negative_int),
    "devices": _devices,
    "accelerator": _registered("accelerator", _accelerators),
    "strategy": _registered("strategy", _strategies),
    "num_nodes": positive_int,
    "log_every_n_steps": optional(positive_int),
    "check_val_every_n_epoch": optional(positive_int),
    "accumulate_grad_batches": positive_int,
    "reload_dataloaders_every_n_epochs": non_negative_int,
    "gradient_clip_val": optional(non_negative),
    "gradient_clip_algorithm": _one_of(None, "norm", "value"),
    "limit_train_batches": _batches,
    "limit_val_batches": _batches,
    "limit_test_batches": _batches,
    "limit_predict_batches": _batches,
    "fast_dev_run": lambda v: (
        None
        if isinstance(v, bool) or (_integer(v) and v >= 0)
        else ("must be true, false or a number of batches >= 0")
    ),
    "num_sanity_val_steps": lambda v: (
        None
        if v is None or (_integer(v) and v >= -1)
        else ("must be an integer >= -1 (-1: every validation batch) or null")
    ),
}
SCHEDULER_RANGES = {"step_size": positive_int, "T_max": positive_int, "gamma": positive}
NET_RANGES = {
    name: positive_int
    for name in ("out_dim", "in_channels", "image_size", "hidden", "latent", "pair_channels")
} | {
    name: lambda v: (
        None
        if isinstance(v, (list, tuple)) and v and all(_integer(c) and c > 0 for c in v)
        else "must be a non-empty list of positive integers"
    )
    for name in ("channels", "point_channels", "head_channels")
}
CHECKPOINT_RANGES = {
    "mode": _one_of("min", "max"),
    "save_top_k": lambda v: None if _integer(v) and v >= -1 else "must be an integer >= -1",
    "every_n_epochs": optional(non_negative_int),
    "every_n_train_steps": optional(non_negative_int),
}


# --- the targets our configs use ---------------------------------------------------------------
