"""The package's error base class: every error a user can act on derives from it."""

from __future__ import annotations


class CloeError(Exception):
    """A problem with the user's input, reported with a message that says what to change."""


class ConfigError(CloeError, ValueError):
    """Settings (of an estimator, identifier, engine) that cannot be used."""
