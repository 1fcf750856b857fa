"""Parameters from YAML files (``--ros-args --params-file FILE``) and refused at run time.

* The shipped ``config/inference.yaml`` and ``config/sim.yaml`` start their nodes, and every value
  in them is what the running node reports (read back with a parameter client from this process).
* A file with a value the node cannot use (out of range, wrong type, unknown algorithm, 3 gains
  for 12 states, a rate that does not divide the integration rate, an unknown scenario) ends the
  process with status 1 and ``ERROR: ...`` on stderr naming the parameter, no traceback.
* A running ``cloe_inference`` refuses, through its ``set_parameters`` service called from
  another process, an out-of-range or mistyped ``rate``, a read-only ``vehicles``, an unknown
  ``algorithm`` and 3 ``sm_gains``, with the reason, and keeps its values; a valid change is
  applied (so the refusals are the node's, not a broken client's).
"""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import (
    REPO,
    NodeProcess,
    private_domain,
    reserve_domain_id,
    spin_until,
    start_node,
)

from cloe_ros.ros.inference_node import KERNELS_NOTE

pytestmark = pytest.mark.ros

CONFIG = REPO / 'config'


def logs(proc: NodeProcess) -> str:
    return proc.output()


@pytest.fixture
def ros():
    """A domain of our own with an rclpy context and a node on it, to call parameter services."""
    with private_domain('params_test') as ros:
        yield ros


class Client:
    """``AsyncParameterClient`` calls, each spun to completion."""

    def __init__(self, ros, node_name: str) -> None:
        self.ros = ros
        self.client = AsyncParameterClient(ros.node, node_name)
        assert self.client.wait_for_services(timeout_sec=60.0), f'{node_name} has no services'

    def _result(self, future):
        assert spin_until(self.ros.executor, future.done, timeout=60.0)
        return future.result()

    def get(self, names: list[str]) -> dict:
        """Values by name; a name the node does not have is left out (the service answers a
        request naming one with no values at all, so each name is asked on its own)."""
        out = {}
        for name in names:
            values = self._result(self.client.get_parameters([name])).values
            if values:
                out[name] = parameter_value_to_python(values[0])
        return out

    def set(self, name: str, value):
        (result,) = self._result(
            self.client.set_parameters([Parameter(name, value=value)])
        ).results
        return result


def same(a, b) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return math.isclose(float(a), float(b), rel_tol=0, abs_tol=0)
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b


def yaml_values(path: Path, node_name: str) -> dict:
    return yaml.safe_load(path.read_text())[node_name]['ros__parameters']


# -- the shipped files ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('executable', 'config', 'ready'),
    [
        ('cloe_inference', 'inference.yaml', 'ready:'),
        ('quadrotor_sim', 'sim.yaml', 'started'),
    ],
)
def test_shipped_config_starts_the_node(ros, tmp_path, executable, config, ready) -> None:
    path = CONFIG / config
    values = yaml_values(path, executable)
    proc = start_node(executable, {}, ros.domain, tmp_path, ['--params-file', str(path)])
    try:
        assert proc.wait_for(ready, 120.0), logs(proc)
        got = Client(ros, executable).get(sorted(values))
        status = proc.stop(signal.SIGINT)
    finally:
        proc.stop(signal.SIGKILL)
    out = logs(proc)
    assert status == 0 and 'Traceback' not in out and 'ERROR' not in out, out
    assert set(got) == set(values), (
        f'{config}: not parameters of the node: {set(values) - set(got)}'
    )
    differ = {n: (values[n], got[n]) for n in values if not same(values[n], got[n])}
    assert not differ, f'{config} values not taken (file, node): {differ}'
    if executable == 'cloe_inference':
        # the log says the algorithm and rate the file gives, and the kernels the node runs: the
        # ones built ahead where the installed package has them (make install builds them)
        assert f'ready: {values["algorithm"]} at {values["rate"]:g} Hz' in out
        assert KERNELS_NOTE['ahead' if installed_kernels_built() else 'jit'] in out, out


def installed_kernels_built() -> bool:
    """Whether the installed package (the nodes') has its kernels built ahead, current."""
    code = 'from cloe_ros.core import ahead; print(ahead.module_path().is_file())'
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'CLOE_ROS_KERNELS')}
    done = subprocess.run([sys.executable, '-c', code], env=env, cwd='/', capture_output=True,
                          text=True, timeout=120, check=True)  # fmt: skip
    return done.stdout.split() == ['True']


# -- files the nodes refuse ---------------------------------------------------------------------

BAD_FILES = [
    ('cloe_inference', {'rate': 5000.0},
     r"ERROR: parameter 'rate': .*out of range Min: 1.0, Max: 2000.0, value: 5000.0"),
    ('cloe_inference', {'rate': 'fast'},
     r"ERROR: parameter 'rate': .*'fast' of type 'STRING', expecting type 'DOUBLE'"),
    ('cloe_inference', {'algorithm': 'kalman'},
     r"ERROR: parameter 'algorithm': 'kalman' is not one of cloe, cloe_sm, cloe_iv"),
    ('cloe_inference', {'sm_gains': [0.1, 0.2, 0.3]},
     r"ERROR: parameter 'sm_gains': needs 12 numbers, one per state, got 3"),
    ('quadrotor_sim', {'odom_rate': 300.0},
     r"ERROR: parameter 'odom_rate': 300 Hz does not divide sim_rate 1000 Hz"),
    ('quadrotor_sim', {'scenario': 'loop'},
     r"ERROR: parameter 'scenario': 'loop' is not one of position, trajectory, hover"),
]  # fmt: skip


@pytest.mark.parametrize(
    ('executable', 'values', 'reason'),
    BAD_FILES,
    ids=['rate-range', 'rate-type', 'algorithm', 'sm_gains-3', 'sim-odom_rate', 'sim-scenario'],
)
def test_bad_yaml_stops_the_node_with_a_reason(tmp_path, executable, values, reason) -> None:
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump({executable: {'ros__parameters': values}}))
    proc = start_node(executable, {}, reserve_domain_id(), tmp_path, ['--params-file', str(path)])
    try:
        status = proc.wait(120.0)
    finally:
        proc.stop(signal.SIGKILL)
    err = proc.errors()
    assert status == 1, logs(proc)
    assert re.search(reason, err), err
    assert 'Traceback' not in logs(proc) and 'ready:' not in logs(proc)


# -- refusals at run time ------------------------------------------------------------------------


def test_running_node_refuses_bad_values(ros, tmp_path) -> None:
    proc = start_node('cloe_inference', {'algorithm': 'cloe_sm'}, ros.domain, tmp_path)
    try:
        assert proc.wait_for('ready:', 120.0), logs(proc)
        client = Client(ros, 'cloe_inference')
        result = client.set('rate', 5000.0)
        assert not result.successful and 'rate' in result.reason and 'range' in result.reason
        result = client.set('rate', 'fast')
        assert not result.successful and 'type' in result.reason.lower()
        result = client.set('vehicles', ['/uav1'])
        assert not result.successful and 'read-only' in result.reason
        assert 'vehicles' in result.reason
        result = client.set('algorithm', 'kalman')
        assert not result.successful
        assert result.reason == "algorithm 'kalman' is not one of cloe, cloe_sm, cloe_iv"
        result = client.set('sm_gains', [0.1, 0.2, 0.3])
        assert not result.successful and 'sm_gains' in result.reason
        # unchanged ('vehicles' cannot be read back: declared without a value when not given, it
        # is "uninitialized", and a GetParameters request naming it returns no values at all)
        kept = client.get(['rate', 'algorithm', 'sm_gains'])
        assert kept['rate'] == 100.0 and kept['algorithm'] == 'cloe_sm'
        assert len(kept['sm_gains']) == 12
        # a value the node can use is applied (it restarts its estimators at the new rate)
        result = client.set('rate', 50.0)
        assert result.successful, result.reason
        assert proc.wait_for('restarted the estimators: cloe_sm at 50 Hz', 60.0)
        assert client.get(['rate']) == {'rate': 50.0}
        status = proc.stop(signal.SIGINT)
    finally:
        proc.stop(signal.SIGKILL)
    assert status == 0, logs(proc)
