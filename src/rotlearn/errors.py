"""Errors that name the config key or the training step at fault."""

from __future__ import annotations

__all__ = ["ConfigValueError", "NonFiniteError", "batch_index", "require_positive_ints"]


class ConfigValueError(ValueError):
    """A config value is out of range. `key` is relative to the component's config node."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


class NonFiniteError(FloatingPointError):
    """A tensor holds NaN or inf during training or evaluation."""


def require_positive_ints(**values: float) -> None:
    """Raise `ConfigValueError` naming the first key whose value is not a positive integer."""
    for key, value in values.items():
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ConfigValueError(key, f"must be a positive integer, got {value}")


def batch_index(flat: int, shape: tuple[int, ...]) -> tuple[int, ...]:
    """The multi-index, in a batch of `shape`, of the `flat`-th element in row-major order."""
    index = []
    for size in reversed(shape):
        index.append(flat % size)
        flat //= size
    return tuple(reversed(index))
