"""A command line a node cannot start with ends in one ``ERROR:`` line and exit status 1.

Every node's console script is run as a process with a ``--params-file`` that is missing, not
YAML, or not laid out as rcl expects; rclpy alone ends each of these in an ``RCLError`` traceback
(or, for a file that is not a mapping, starts without a word).
"""

from __future__ import annotations

import subprocess

import pytest
from ros_helpers import executable, reserve_domain_id, ros_env

from cloe_ros.ros.common import StartupError, check_params_files, params_files

pytestmark = pytest.mark.ros

NODES = ('quadrotor_sim', 'cloe_inference', 'bag_recorder', 'bag_player')

MALFORMED = {
    'syntax': ('node:\n  ros__parameters:\n    rate: [1, 2\n', 'not valid YAML at line 4'),
    'scalar': ('just some text\n', 'expected a mapping of node names to ros__parameters'),
    'value-above': ('cloe_inference:\n  rate: 5\n', 'cloe_inference/rate is a value outside'),
    'params-not-mapping': (
        'cloe_inference:\n  ros__parameters: 5\n',
        'cloe_inference/ros__parameters must be a mapping',
    ),
    'no-node': ('ros__parameters:\n  rate: 5\n', 'ros__parameters must be under a node name'),
    # (what rcl refuses with its own words, said before it: cloe_ros.io.param_sections)
    'bad-name': ('cloe-x:\n  ros__parameters: {rate: 5.0}\n', "rcl accepts: 'cloe-x'"),
    'params-null': ('cloe_inference:\n  ros__parameters:\n', 'ros__parameters has no value'),
    'alias': ('a: &x {ros__parameters: {rate: 5.0}}\nb: *x\n', 'rcl does not support aliasing'),
}


def run_node(tmp_path, name: str, *args: str) -> tuple[int, str]:
    proc = subprocess.run(
        [executable(name), *args],
        env=ros_env(reserve_domain_id(), tmp_path / 'ros_log'),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return proc.returncode, proc.stdout + proc.stderr


def assert_one_error_line(out: str, *expected: str) -> None:
    assert 'Traceback' not in out and 'RCLError' not in out, out
    errors = [line for line in out.splitlines() if 'ERROR' in line]
    assert len(errors) == 1 and errors[0].startswith('ERROR: '), out
    for text in expected:
        assert text in errors[0], out


@pytest.mark.parametrize('name', NODES)
def test_missing_params_file(tmp_path, name):
    missing = tmp_path / 'nonexistent.yaml'
    status, out = run_node(tmp_path, name, '--ros-args', '--params-file', str(missing))
    assert status == 1, out
    assert_one_error_line(out, f'parameter file {missing}: it does not exist')


@pytest.mark.parametrize('name', NODES)
def test_malformed_params_file(tmp_path, name):
    bad = tmp_path / 'bad.yaml'
    bad.write_text(MALFORMED['syntax'][0])
    status, out = run_node(tmp_path, name, '--ros-args', '--params-file', str(bad))
    assert status == 1, out
    assert_one_error_line(out, f'parameter file {bad}: ', MALFORMED['syntax'][1])


def test_other_bad_arguments_are_one_line_too(tmp_path):
    """What rcl refuses beyond the files (here a remap rule without ``:=``): its reason, once."""
    status, out = run_node(tmp_path, 'cloe_inference', '--ros-args', '-r', 'odom')
    assert status == 1, out
    assert_one_error_line(out, "ERROR: cannot start: Couldn't parse remap rule: '-r odom'")
    assert '.c:' not in out  # no C source locations


@pytest.mark.parametrize('case', sorted(MALFORMED))
def test_check_params_files(tmp_path, case):
    text, expected = MALFORMED[case]
    path = tmp_path / f'{case}.yaml'
    path.write_text(text)
    with pytest.raises(StartupError, match=expected.replace('[', r'\[')):
        check_params_files(['node', '--ros-args', '--params-file', str(path)])


def test_check_params_files_accepts_what_rcl_accepts(tmp_path):
    good = tmp_path / 'good.yaml'
    good.write_text(
        'cloe_inference:\n  ros__parameters:\n    rate: 50.0\n'
        '/**:\n  ros__parameters:\n    use_sim_time: false\n'
        'uav1:\n  cloe_inference:\n    ros__parameters: {algorithm: cloe_iv}\n'
    )
    empty = tmp_path / 'empty.yaml'
    empty.write_text('')
    argv = ['n', '--ros-args', '--params-file', str(good), '--', '--ros-args',
            '--params-file', str(empty)]  # fmt: skip
    assert params_files(argv) == [str(good), str(empty)]
    check_params_files(argv)
    # outside --ros-args, --params-file is the program's own argument
    assert params_files(['n', '--params-file', '/nonexistent.yaml']) == []
