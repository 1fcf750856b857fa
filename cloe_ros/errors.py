"""The package's errors: one hierarchy under :class:`CloeError`, one module per layer.

Every error a user can act on derives from :class:`CloeError`; the ``cloe`` command prints it as
one ``ERROR: ...`` line (exit status 1) and a node as ``ERROR: ...`` at start-up. The tree::

    CloeError
    ├── ConfigError (a ValueError too)  a setting that cannot be used        cloe_ros.errors
    │   ├── OutputConfigError           the output settings (namespace, rate)  cloe_ros.io.errors
    │   ├── ParameterError              a node parameter ("parameter 'x': ")  cloe_ros.ros.errors
    │   └── StartupError                a node's command line (--params-file)  cloe_ros.ros.errors
    ├── BagError                        a bag that cannot be read            cloe_ros.io.errors
    │   └── RecoverError                a bag that cannot be recovered       cloe_ros.io.errors
    ├── WriterError                     a bag that cannot be written         cloe_ros.io.errors
    ├── MessageError                    CDR that cannot be decoded/encoded   cloe_ros.io.errors
    └── CliError                        a command line that cannot be run    cloe_ros.cli.errors

All of them are importable from :mod:`cloe_ros` (none of these modules imports rclpy).
``ConfigError`` covers every invalid setting: the core's configuration dataclasses, the settings
of ``cloe infer --config`` (``cloe_ros.io.config.SettingsError`` is the same class, kept under
that name for its importers), the outputs and, through ``ParameterError``, the nodes'
parameters. Each class is also importable from the modules that raise it
(``cloe_ros.io.reader.BagError``, ``cloe_ros.io.writer.WriterError``,
``cloe_ros.io.recover.RecoverError``, ``cloe_ros.io.messages.MessageError``,
``cloe_ros.io.outputs.OutputConfigError``, ``cloe_ros.ros.common.ParameterError``). The MCAP
record parser's ``RecordError`` and the reader's ``_Damage`` are internal: the reader and
recovery translate them into a ``BagError`` / ``RecoverError`` naming the file; so is
``cloe_ros.io.param_sections.ParamFileError``, which ``cloe infer --config`` and a node's
start-up translate into a ``ConfigError`` / ``StartupError`` naming the parameter file.
"""

from __future__ import annotations


class CloeError(Exception):
    """A problem with the user's input, reported with a message that says what to change."""


class ConfigError(CloeError, ValueError):
    """A setting (of an estimator, identifier, engine, the outputs, a settings file) that cannot be
    used; the message says which and why.

    ``name`` is the setting at fault (None when no single one is) and ``reason`` the message after
    the name, so that a node can report ``parameter '<name>': <reason>``. ``ConfigError(reason)``
    alone is the message as it is.
    """

    def __init__(self, reason: str, name: str | None = None) -> None:
        super().__init__(f'{name} {reason}' if name else reason)
        self.name, self.reason = name, reason
