"""Errors of the bag layer (no rclpy): reading, recovering and writing bags.

Each is re-exported by the module that raises it (:mod:`cloe_ros.io.reader`,
:mod:`cloe_ros.io.recover`, :mod:`cloe_ros.io.writer`); the whole tree is in
:mod:`cloe_ros.errors`.
"""

from __future__ import annotations

from cloe_ros.errors import CloeError

__all__ = ['BagError', 'RecoverError', 'WriterError']


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
