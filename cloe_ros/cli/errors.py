"""Errors of the command line."""

from __future__ import annotations

from cloe_ros.errors import CloeError


class CliError(CloeError):
    """A problem with the command line that the CLI reports as ``ERROR: ...``, exit status 1."""
