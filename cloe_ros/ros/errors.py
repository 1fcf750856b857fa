"""Errors of the node layer: a node's parameters and command line.

This module imports no rclpy, so that :mod:`cloe_ros` can re-export its classes; they are also
importable from :mod:`cloe_ros.ros.common`, which raises them.
"""

from __future__ import annotations

from cloe_ros.errors import ConfigError

__all__ = ['ParameterError', 'StartupError']


class StartupError(ConfigError):
    """The command line names something the node cannot start with (reported, exit status 1)."""


class ParameterError(ConfigError):
    """A parameter value the node cannot start with (reported, exit status 1).

    The message is ``parameter '<name>': <reason>`` (the documented form), or the reason alone
    for a problem no single parameter has."""

    def __init__(self, reason: str, name: str | None = None) -> None:
        super().__init__(f'parameter {name!r}: {reason}' if name else reason)
        self.name, self.reason = name, reason
