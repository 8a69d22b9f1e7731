"""The NaN/inf check of a LightningModule's steps, without a host sync per step.

Each step's tensors are *observed*: a few device ops record their NaN and inf counts (and whether
the step's input batch was itself non-finite) on the device; nothing waits for the device. The
record is *read* (one host sync) every `finite_check_every` training steps, at the last batch of
every epoch (before validation and checkpoints), at the end of every validation/test/predict loop
and when fitting ends; a failure then raises `NonFiniteError` naming the stage, step, epoch and
batch that failed FIRST, the tensor, its counts and the likely cause. Between a failure and its
read no update is applied: the gradients are zeroed on the device before every optimizer step once
the record holds a failure, so the weights stay what they were (`finite_check_every=1` reads every
step, as a debugging aid).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from rotlearn.errors import NonFiniteError

__all__ = ["FINITE_CHECK_EVERY", "FiniteChecks", "FiniteRecord"]

FINITE_CHECK_EVERY = 50  # training steps between two reads of the record (model.finite_check_every)


class FiniteRecord:
    """Device-side record of the tensors observed since the last read: per observation, its NaN
    and inf counts and whether its step's input batch was non-finite (3 int64 on the device).

    `observe` queues a handful of device ops (no sync); `read` copies the rows to the host once,
    returns the first failure and starts a new record. The facts known on the host (name, stage,
    step, shape) are kept per observation beside the rows.
    """

    def __init__(self) -> None:
        self._observed: list[tuple[Any, ...]] = []
        self._rows: list[Tensor] = []  # (3,) int64 per observation: NaN, inf, input non-finite
        self._failed: Tensor | None = None  # 0-d bool: some observation was non-finite

    def observe(self, value: Tensor, facts: tuple[Any, ...], inputs_bad: Tensor | None) -> None:
        """Record the NaN and inf counts of `value` (any shape).

        Args:
            value: the tensor checked (detached here).
            facts: host-side facts returned by `read` with the counts (name, stage, step, ...).
            inputs_bad: 0-d bool tensor, True when the step's input batch holds NaN/inf; or None.
        """
        value = value.detach()
        self._observed.append((*facts, tuple(value.shape)))
        n_nan, n_inf = torch.isnan(value).sum(), torch.isinf(value).sum()
        bad_in = torch.zeros_like(n_nan) if inputs_bad is None else inputs_bad.to(n_nan.dtype)
        self._rows.append(torch.stack([n_nan, n_inf, bad_in]))
        bad = (n_nan + n_inf) > 0
        self._failed = bad if self._failed is None else self._failed | bad

    def failed(self) -> Tensor | None:
        """0-d bool device tensor: a failure is recorded (None before the first observation)."""
        return self._failed

    def read(self) -> dict[str, Any] | None:
        """The first failure since the last read (host sync), or None; starts a new record."""
        if not self._rows:
            return None
        rows = torch.stack(self._rows).tolist()
        observed = self._observed
        self._observed, self._rows, self._failed = [], [], None
        index = next((i for i, (nan, inf, _) in enumerate(rows) if nan + inf), None)
        if index is None:
            return None
        *facts, shape = observed[index]
        n_nan, n_inf, bad_in = rows[index]
        return {"facts": tuple(facts), "shape": shape, "nan": n_nan, "inf": n_inf,
                "inputs_bad": bool(bad_in)}  # fmt: skip


class FiniteChecks:
    """Mixin for rotlearn's LightningModules: the deferred NaN/inf check (module docstring).

    The module calls `_init_finite_checks(every)` in `__init__`, `_observe(...)` on its step
    tensors, and `_read_finite()` at the start of its `on_{validation,test,predict}_epoch_end`;
    the training reads are the hooks here.
    """

    finite_check_every: int = FINITE_CHECK_EVERY

    def _init_finite_checks(self, every: int) -> None:
        self.finite_check_every = int(every)  # > 0: the modules' signatures say so
        self._finite = FiniteRecord()
        self._steps_since_read = 0

    def _observe(
        self, name: str, value: Tensor, stage: str, batch_idx: int, inputs_bad: Tensor | None
    ) -> None:
        facts = (name, stage, self.global_step, self.current_epoch, batch_idx)
        self._finite.observe(value, facts, inputs_bad)

    @staticmethod
    def _inputs_bad(batch: dict[str, Tensor]) -> Tensor | None:
        """0-d bool device tensor: the batch's input holds NaN/inf (None: no input tensor)."""
        inputs = batch.get("input")
        return None if inputs is None else ~torch.isfinite(inputs).all()

    def _check_finite(self, name: str, value: Tensor, batch: dict, stage: str, idx: int) -> None:
        """Observe `value` and read at once (a host sync): the check of one tensor, now."""
        self._observe(name, value, stage, idx, self._inputs_bad(batch))
        self._read_finite()

    def _read_finite(self) -> None:
        """Read the record (one host sync); raise `NonFiniteError` on a recorded failure. Under
        DDP every rank learns that one failed, so that all stop together."""
        self._steps_since_read = 0
        failure = self._finite.read()
        strategy = getattr(getattr(self, "_trainer", None), "strategy", None)
        anywhere = failure is not None
        if strategy is not None:
            anywhere = strategy.reduce_boolean_decision(anywhere, all=False)
        if anywhere and failure is None:
            raise NonFiniteError(
                f"another process saw a non-finite tensor (before step {self.global_step}, "
                f"epoch {self.current_epoch}); its own message names it"
            )
        if failure is None:
            return
        name, stage, step, epoch, batch_idx = failure["facts"]
        shape = failure["shape"]
        numel = int(torch.Size(shape).numel())
        counts = f"{failure['nan']} NaN and {failure['inf']} inf"
        detail = f"{counts} among {numel} entries of shape {shape}"
        where = f"{stage} step {step} (epoch {epoch}, batch {batch_idx})"
        raise NonFiniteError(
            f"non-finite {name} at {where}: {detail}; {self._cause(failure['inputs_bad'])}"
        )

    def _cause(self, inputs_bad: bool) -> str:
        """Why a tensor is non-finite: the batch, weights already non-finite, or an overflow from
        finite inputs and weights. Only the last two blame the training. (The weights are looked
        at when the record is read: no update was applied since the failure.)"""
        if inputs_bad:
            return "the input batch is itself non-finite (check the dataset files)"
        bad = next((n for n, p in self.named_parameters() if not bool(p.isfinite().all())), None)
        if bad is not None:
            return (
                f"the inputs are finite, but the weights are not (first: {bad}): they diverged "
                "in an earlier step (try a lower optim.lr) or were initialised from bad data"
            )
        return (
            "the inputs and the weights are finite: the computation overflowed "
            "(try a lower optim.lr)"
        )

    # --- training: zero the update after a failure; read every N steps and at the epoch's end

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        failed = self._finite.failed()
        if failed is None:
            return
        for group in optimizer.param_groups:
            for parameter in group["params"]:
                if parameter.grad is not None:
                    parameter.grad.masked_fill_(failed, 0.0)

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        self._steps_since_read += 1
        last = batch_idx + 1 >= self.trainer.num_training_batches
        if last or self._steps_since_read >= self.finite_check_every:
            self._read_finite()

    def on_train_end(self) -> None:
        self._read_finite()  # fitting stopped mid-epoch (max_steps, a signal)
