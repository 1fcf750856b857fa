"""One error hierarchy under CloeError: every error a user can act on is one, each layer's errors
are importable where they are raised, and every invalid setting is a ConfigError."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import cloe_ros
from cloe_ros.cli.errors import CliError
from cloe_ros.errors import CloeError, ConfigError
from cloe_ros.io import errors as io_errors
from cloe_ros.io.config import SettingsError, build_configs
from cloe_ros.io.messages import MessageError
from cloe_ros.io.outputs import OutputConfig, OutputConfigError
from cloe_ros.io.reader import BagError
from cloe_ros.io.recover import RecoverError
from cloe_ros.io.writer import WriterError


def test_every_error_is_a_cloe_error():
    for cls in (ConfigError, BagError, RecoverError, WriterError, MessageError, CliError):
        assert issubclass(cls, CloeError), cls
    assert issubclass(RecoverError, BagError)
    # the io layer's errors are one set of classes, re-exported where they are raised
    assert (BagError, RecoverError, WriterError, MessageError, OutputConfigError) == (
        io_errors.BagError, io_errors.RecoverError, io_errors.WriterError,
        io_errors.MessageError, io_errors.OutputConfigError)  # fmt: skip


#: Error classes that never reach a user: the reader and recovery translate them into a BagError
#: or RecoverError naming the file, the settings and a node's start-up a parameter file's into a
#: ConfigError or StartupError naming it.
INTERNAL_ERRORS = {'RecordError', '_Damage', 'ParamFileError'}


def test_every_error_class_of_the_package_is_in_the_tree_and_exported_by_cloe_ros():
    """No error class outside the hierarchy: each one the package defines is re-exported by
    ``cloe_ros`` and is a CloeError, apart from the internal ones."""
    root = Path(cloe_ros.__file__).parent
    defined = {
        node.name: path.relative_to(root).as_posix()
        for path in root.rglob('*.py')
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8')))
        if isinstance(node, ast.ClassDef) and node.name.lstrip('_').endswith(('Error', 'Damage'))
    }
    assert 'ParameterError' in defined and 'RecordError' in defined  # the scan finds them
    public = {name for name in defined if name not in INTERNAL_ERRORS}
    assert public <= set(cloe_ros.__all__), (public - set(cloe_ros.__all__), defined)
    for name in public:
        assert issubclass(getattr(cloe_ros, name), cloe_ros.CloeError), name


def test_cloe_ros_exports_the_errors_without_importing_rclpy():
    code = (
        'import sys, cloe_ros; '
        "print(cloe_ros.ParameterError.__mro__[1].__name__, 'rclpy' in sys.modules)"
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ['ConfigError', 'False']


def test_every_invalid_setting_is_a_config_error():
    assert SettingsError is ConfigError
    assert issubclass(ConfigError, ValueError)  # what callers caught before
    with pytest.raises(ConfigError) as info:
        OutputConfig('not a namespace!')
    assert isinstance(info.value, OutputConfigError) and isinstance(info.value, ValueError)
    assert (info.value.name, str(info.value)) == (
        'output_ns', "output_ns 'not a namespace!' is not a valid namespace")  # fmt: skip
    with pytest.raises(OutputConfigError, match=r'^parameters_rate must be within \[0.01, '):
        OutputConfig(parameters_rate=0.0)
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
