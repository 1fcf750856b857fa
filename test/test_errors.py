"""One error hierarchy under CloeError: every error a user can act on is one, each layer's errors
are importable where they are raised, and every invalid setting is a ConfigError."""

from __future__ import annotations

import pytest

from cloe_ros.cli.errors import CliError
from cloe_ros.errors import CloeError, ConfigError
from cloe_ros.io import errors as io_errors
from cloe_ros.io.config import SettingsError, build_configs
from cloe_ros.io.messages import MessageError
from cloe_ros.io.reader import BagError
from cloe_ros.io.recover import RecoverError
from cloe_ros.io.writer import WriterError


def test_every_error_is_a_cloe_error():
    for cls in (ConfigError, BagError, RecoverError, WriterError, MessageError, CliError):
        assert issubclass(cls, CloeError), cls
    assert issubclass(RecoverError, BagError)
    # the io layer's errors are one set of classes, re-exported where they are raised
    assert (BagError, RecoverError, WriterError) == (
        io_errors.BagError, io_errors.RecoverError, io_errors.WriterError)  # fmt: skip


def test_every_invalid_setting_is_a_config_error():
    assert SettingsError is ConfigError
    assert issubclass(ConfigError, ValueError)  # what callers caught before
    with pytest.raises(ConfigError) as info:
        build_configs({'rate': 0.5})
    assert (info.value.name, str(info.value)) == ('rate', 'rate must be within [1, 2000], got 0.5')


def test_a_node_parameter_error_is_a_config_error():
    from cloe_ros.ros.common import ParameterError

    err = ParameterError('must be positive', 'rate')
    assert isinstance(err, ConfigError) and isinstance(err, CloeError)
    assert (str(err), err.name, err.reason) == ("parameter 'rate': must be positive", 'rate',
                                                'must be positive')  # fmt: skip
    assert str(ParameterError('nothing to play')) == 'nothing to play'
