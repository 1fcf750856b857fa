"""The core and the io layer (and the package root with its errors) never import rclpy or ROS
message packages: every module under cloe_ros.core and cloe_ros.io is imported under a hook that
refuses them."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import cloe_ros.core
import cloe_ros.io
from cloe_ros.core import ahead

SCRIPT = r'''
import importlib, sys

class Block:
    """Refuse rclpy, rosidl and *_msgs imports so an indirect import fails loudly."""
    def find_spec(self, name, path=None, target=None):
        top = name.split('.')[0]
        if top in ('rclpy', 'rosidl_runtime_py', 'rosbag2_py') or top.endswith('_msgs'):
            raise ImportError(f'core or io imported {name}')
        return None

sys.meta_path.insert(0, Block())
for name in sys.argv[1:]:
    importlib.import_module(name)
bad = [m for m in sys.modules if m.split('.')[0] == 'rclpy' or m.split('.')[0].endswith('_msgs')]
assert not bad, bad
print('ok', len(sys.argv) - 1)
'''


def _modules(package):
    """The package's modules; not the kernels built ahead, an extension module that only
    cloe_ros.core.ahead loads (after the OpenBLAS it calls: imported alone, it does not link)."""
    return [m.name for m in pkgutil.walk_packages(package.__path__, package.__name__ + '.')
            if not m.name.rsplit('.', 1)[1].startswith(ahead.PREFIX)]  # fmt: skip


def test_no_module_under_core_or_io_imports_rclpy():
    modules = ['cloe_ros', 'cloe_ros.errors', *_modules(cloe_ros.core), *_modules(cloe_ros.io)]
    assert 'cloe_ros.core.estimator' in modules and 'cloe_ros.core.simulator' in modules
    assert 'cloe_ros.io.reader' in modules and 'cloe_ros.io.messages' in modules
    out = subprocess.run([sys.executable, '-c', SCRIPT, *modules], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f'ok {len(modules)}'


def test_the_block_catches_an_rclpy_import():
    """The check above can fail: importing rclpy under the same hook is refused."""
    out = subprocess.run([sys.executable, '-c', SCRIPT, 'rclpy'], capture_output=True, text=True)
    assert out.returncode != 0 and 'core or io imported rclpy' in out.stderr
