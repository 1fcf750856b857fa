"""Helpers for tests that use rclpy or start node processes.

* :func:`reserve_domain_id` (the package's, given back when the test ends) hands out a
  ``ROS_DOMAIN_ID`` no other process on this machine holds (a lock file per id), so
  process-level tests never see each other's nodes.
* :func:`start_node` starts a node's installed console script on a given domain as the package's
  own :class:`~cloe_ros.cli.processes.NodeProcess` (what ``cloe demo`` uses), standard output and
  standard error each in a file of its own; ``stop()`` ends it with a chosen signal.
* :func:`spin_until` spins an executor until a condition holds or a timeout passes.
* :func:`private_domain` gives a test a domain of its own with an rclpy context, a node and an
  executor on it.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

from cloe_ros.cli.processes import NodeProcess, release_domain_id
from cloe_ros.cli.processes import reserve_domain_id as _reserve
from cloe_ros.cli.processes import ros_env as node_env

__all__ = [
    'NodeProcess',
    'executable',
    'private_domain',
    'release_test_domains',
    'reserve_domain_id',
    'ros_env',
    'shared_memory_segments',
    'spin_until',
    'start_node',
]

REPO = Path(__file__).resolve().parent.parent
#: Domains reserved by the running test (released after it: release_test_domains).
_TEST_DOMAINS: list[int] = []


def reserve_domain_id() -> int:
    """A domain of its own for a test (:func:`cloe_ros.cli.processes.reserve_domain_id`), given
    back when the test ends (``test/conftest.py`` calls :func:`release_test_domains`): a suite
    reserves hundreds over its run, and the machine has 130, shared with the suites of other
    work trees running beside it."""
    domain = _reserve()
    _TEST_DOMAINS.append(domain)
    return domain


def release_test_domains() -> None:
    """Give back every domain the test that just ended reserved (its nodes are stopped)."""
    while _TEST_DOMAINS:
        release_domain_id(_TEST_DOMAINS.pop())


def ros_env(domain_id: int, log_dir: Path | None = None) -> dict[str, str]:
    """Environment for a node process on ``domain_id``, DDS on localhost only, rcl logs in
    ``log_dir`` (default: one folder under the system's temporary directory)."""
    env = node_env(domain_id, log_dir or Path(tempfile.gettempdir()) / 'cloe_ros_test_logs')
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


#: A Fast DDS profile with UDP on the loopback interface as the only transport (no shared
#: memory); see :func:`start_node`'s ``udp_only``.
UDP_LOOPBACK_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>udp_loopback</transport_id>
      <type>UDPv4</type>
      <interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="udp_loopback" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>udp_loopback</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""


def udp_only_env(env: dict[str, str], workdir: Path) -> dict[str, str]:
    """``env`` changed so that the node's DDS participant speaks UDP on 127.0.0.1 only, without
    Fast DDS's shared-memory transport.

    A test that stops a node (SIGSTOP) needs this. When a process opens a shared-memory port,
    Fast DDS checks that the port's reader answers within a second, and removes the port and
    creates it anew if it does not. A stopped reader cannot answer; when it runs again it can find
    its own port marked broken and read nothing more on it, and a later process on the same
    domain reuses the port's number. Over UDP a stopped reader only fills its socket buffer, which
    reliable delivery repairs. rmw_fastrtps keeps shared memory under
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` whatever the profile says, so the range is SUBNET,
    with the UDP transport restricted to the loopback interface and 127.0.0.1 as a static peer:
    nothing leaves the machine."""
    profile = workdir / 'udp_loopback.xml'
    profile.write_text(UDP_LOOPBACK_PROFILE)
    return {
        **env,
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET',
        'ROS_STATIC_PEERS': '127.0.0.1',
        'FASTRTPS_DEFAULT_PROFILES_FILE': str(profile),
    }


def shared_memory_segments(pid: int) -> set[str]:
    """The Fast DDS shared-memory segments (``/dev/shm/fastrtps_*``) process ``pid`` maps."""
    with open(f'/proc/{pid}/maps') as maps:
        return {line.split()[-1] for line in maps if '/dev/shm/fastrtps_' in line}


def start_node(
    name: str,
    params: dict[str, object],
    domain_id: int,
    workdir: Path,
    extra_args: list[str] | None = None,
    node_name: str | None = None,
    udp_only: bool = False,
) -> NodeProcess:
    """The installed console script ``name`` with ``params`` on ``domain_id``, run in ``workdir``
    (rcl logs in ``workdir/ros_log``); its standard output and standard error go to files of
    their own there (``log_path``, ``stderr_path``). ``udp_only``: DDS over UDP on the loopback
    interface without shared memory (:func:`udp_only_env`), for a node the test stops."""
    workdir.mkdir(parents=True, exist_ok=True)
    log_path = workdir / f'{node_name or name}.{os.getpid()}.{time.monotonic_ns()}.out'
    env = ros_env(domain_id, workdir / 'ros_log')
    return NodeProcess(
        name,
        params,
        udp_only_env(env, workdir) if udp_only else env,
        log_path,
        node_name,
        extra_args=extra_args or (),
        command=[executable(name)],
        stderr_path=log_path.with_suffix('.err'),
        cwd=workdir,
    )


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
