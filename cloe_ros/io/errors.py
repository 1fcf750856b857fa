"""Errors of the io layer (no rclpy): reading, recovering and writing bags, decoding and encoding
messages, the output settings.

Each is re-exported by the module that raises it (:mod:`cloe_ros.io.reader`,
:mod:`cloe_ros.io.recover`, :mod:`cloe_ros.io.writer`, :mod:`cloe_ros.io.messages`,
:mod:`cloe_ros.io.outputs`) and by :mod:`cloe_ros`; the whole tree is in :mod:`cloe_ros.errors`.
"""

from __future__ import annotations

from cloe_ros.errors import CloeError, ConfigError

__all__ = ['BagError', 'MessageError', 'OutputConfigError', 'RecoverError', 'WriterError']


class BagError(CloeError):
    """A bag that cannot be read, with a message naming the path and what is wrong."""


class RecoverError(BagError):
    """A bag that cannot be recovered (not a bag, no MCAP file, nothing complete on disk, the
    output exists or cannot be written, ...)."""


class WriterError(CloeError):
    """A bag that cannot be written (existing path, unknown type, closed writer, full disk, ...).

    ``path`` is the bag being written (None when the error is not about one file) and
    ``reason`` the cause of a failed write (the operating system's words, e.g. ``No space left on
    device``), or None.
    """

    def __init__(self, msg: str, path: object = None, reason: str | None = None) -> None:
        super().__init__(msg)
        self.path, self.reason = path, reason


class MessageError(CloeError):
    """Bytes that are not a valid message of the expected type."""


class OutputConfigError(ConfigError):
    """Output settings that cannot be used (``name`` the setting, ``reason`` why)."""
