"""Errors that name the config key or the training step at fault."""

from __future__ import annotations

__all__ = ["ConfigValueError", "NonFiniteError"]


class ConfigValueError(ValueError):
    """A config value is out of range. `key` is relative to the component's config node."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


class NonFiniteError(FloatingPointError):
    """A tensor holds NaN or inf during training or evaluation."""
