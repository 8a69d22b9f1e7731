"""Errors that name the config key or the training step at fault."""

from __future__ import annotations

import re

_SUBJECT = re.compile(r"^(Value error, )?(\w+ )?(?=should )")  # pydantic's "Input should ..."

__all__ = [
    "ConfigError",
    "ConfigValueError",
    "InputAdjustedWarning",
    "NonFiniteError",
    "batch_index",
    "validation_words",
]


class ConfigError(ValueError):
    """A config value that cannot be used, naming its key.

    A component raises it with `key` relative to its own config node (its argument's name,
    e.g. `"phi_max_deg"`); whoever built the component from the node `data` re-raises
    `error.within("data")`, so the message names the full key: `config key data.phi_max_deg: ...`.

    Args:
        key: the config key at fault, dotted.
        message: what is wrong, with the value and what is allowed.
    """

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"config key {key}: {message}")
        self.key = key
        self.message = message

    def within(self, node: str) -> ConfigError:
        """The same error with `key` under the config node `node` (`""`: unchanged)."""
        return ConfigError(f"{node}.{self.key}" if node else self.key, self.message)

    def __reduce__(self):  # picklable (DDP workers, multiprocessing)
        return type(self), (self.key, self.message)


ConfigValueError = ConfigError  # the former name of a component's complaint; the same class


class InputAdjustedWarning(UserWarning):
    """An input was changed to the form the model was trained on (e.g. u_i scaled to unit
    length); `rotlearn-predict` prints it as a note on the input file."""


class NonFiniteError(FloatingPointError):
    """A tensor holds NaN or inf during training or evaluation."""


def batch_index(flat: int, shape: tuple[int, ...]) -> tuple[int, ...]:
    """The multi-index, in a batch of `shape`, of the `flat`-th element in row-major order."""
    index = []
    for size in reversed(shape):
        index.append(flat % size)
        flat //= size
    return tuple(reversed(index))


def validation_words(message: str) -> str:
    """A pydantic error message as rotlearn's config errors word it, after the key: "should be
    a valid list" (pydantic: "Input should be a valid list", "Value error, should be ...")."""
    return _SUBJECT.sub("", message)
