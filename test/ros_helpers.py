"""Helpers for tests that use rclpy or start node processes.

* :func:`reserve_domain_id` (the package's own) hands out a ``ROS_DOMAIN_ID`` no other process on
  this machine holds (a lock file per id), so process-level tests never see each other's nodes.
* :class:`NodeProcess` starts a node executable on a given domain, captures its output to files
  and stops it with a chosen signal.
* :func:`spin_until` spins an executor until a condition holds or a timeout passes.
* :func:`private_domain` gives a test a domain of its own with an rclpy context, a node and an
  executor on it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

from cloe_ros.cli.processes import param_args, reserve_domain_id

__all__ = [
    'NodeProcess',
    'executable',
    'private_domain',
    'reserve_domain_id',
    'ros_env',
    'spin_until',
]

REPO = Path(__file__).resolve().parent.parent


def ros_env(domain_id: int, log_dir: Path | None = None) -> dict[str, str]:
    """Environment for a node process on ``domain_id``, DDS on localhost only."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_LOG_DIR'] = str(log_dir or Path(tempfile.gettempdir()) / 'cloe_ros_test_logs')
    env['PYTHONUNBUFFERED'] = '1'
    # the node processes run the same code as the test process: this source tree
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(REPO), env.get('PYTHONPATH')]))
    return env


def executable(name: str) -> str:
    """Path of an installed console script of the package (next to this Python)."""
    found = shutil.which(name, path=os.path.dirname(sys.executable))
    if found is None:
        raise FileNotFoundError(
            f'{name} is not installed next to {sys.executable}; run `make install`'
        )
    return found


def ros_args(params: dict[str, object]) -> list[str]:
    """``--ros-args -p name:=value ...``."""
    return ['--ros-args', *param_args(params)]


class NodeProcess:
    """A node executable running in its own process group, output captured to files."""

    def __init__(
        self,
        name: str,
        params: dict[str, object],
        domain_id: int,
        workdir: Path,
        extra_args: list[str] | None = None,
    ) -> None:
        self.name = name
        workdir.mkdir(parents=True, exist_ok=True)
        self.stdout_path = workdir / f'{name}.{os.getpid()}.{time.monotonic_ns()}.out'
        self.stderr_path = self.stdout_path.with_suffix('.err')
        self._out = open(self.stdout_path, 'w')
        self._err = open(self.stderr_path, 'w')
        cmd = [executable(name), *ros_args(params), *(extra_args or [])]
        self.proc = subprocess.Popen(
            cmd,
            env=ros_env(domain_id, workdir / 'ros_log'),
            stdout=self._out,
            stderr=self._err,
            cwd=workdir,
            start_new_session=True,
        )

    def output(self) -> str:
        self._out.flush()
        self._err.flush()
        return self.stdout_path.read_text() + self.stderr_path.read_text()

    def wait_for_output(self, text: str, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if self.proc.poll() is not None:
                return text in self.output()
            time.sleep(0.05)
        return False

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Send ``sig`` and wait; kill after ``timeout``. Returns the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self._out.close()
        self._err.close()
        return self.proc.returncode

    def wait(self, timeout: float) -> int:
        self.proc.wait(timeout)
        return self.proc.returncode


def spin_until(executor, condition: Callable[[], bool], timeout: float = 10.0) -> bool:
    """Spin ``executor`` until ``condition()`` is true; False after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        executor.spin_once(timeout_sec=0.05)
    return condition()


@contextmanager
def private_domain(node_name: str) -> Iterator[SimpleNamespace]:
    """A domain of our own (:func:`reserve_domain_id`) with an rclpy context on it, a node named
    ``node_name`` and a single-threaded executor serving it: ``domain``, ``ctx``, ``node``,
    ``executor``. All are shut down on exit."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    domain = reserve_domain_id()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node(node_name, context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        yield SimpleNamespace(domain=domain, ctx=ctx, node=node, executor=executor)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
