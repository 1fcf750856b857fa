"""cloe_ros: online trajectory inference of quadrotors with CLOE / CLOE-SM on ROS 2.

The errors a user can act on are importable from here (the tree: :mod:`cloe_ros.errors`); none
of their modules imports rclpy.
"""

from cloe_ros.cli.errors import CliError
from cloe_ros.errors import CloeError, ConfigError
from cloe_ros.io.errors import BagError, MessageError, OutputConfigError, RecoverError, WriterError
from cloe_ros.ros.errors import ParameterError, StartupError

__version__ = '0.1.0'

__all__ = [
    'BagError',
    'CliError',
    'CloeError',
    'ConfigError',
    'MessageError',
    'OutputConfigError',
    'ParameterError',
    'RecoverError',
    'StartupError',
    'WriterError',
    '__version__',
]
