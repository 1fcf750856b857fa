"""Inference settings shared by the node and ``cloe infer``: ranges, lists, reasons."""

from __future__ import annotations

import array
import math

import numpy as np
import pytest

from cloe_ros.core.estimator import SM_GAINS_TABLE1
from cloe_ros.io import param_sections
from cloe_ros.io.config import (
    DEFAULTS,
    RANGES,
    SettingsError,
    build_configs,
    command_settings,
    load_settings,
)


@pytest.mark.parametrize(
    ('key', 'value'),
    [
        ('rate', 3000.0),
        ('gamma_theta', 2e6),
        ('parameters_rate', 5000.0),
        ('l_initial', 2e4),
        ('l_leak', 2000.0),
        ('ground_altitude', 2000.0),
        ('ground_altitude', -2000.0),
    ],
)
def test_values_the_node_refuses_are_refused(key, value):
    """The node declares these ranges (RANGES); ``cloe infer --config`` takes the same keys, so a
    value out of them is refused here too, naming the key and the range."""
    low, high = RANGES[key]
    assert not low <= value <= high
    with pytest.raises(SettingsError) as info:
        build_configs({key: value})
    assert info.value.name == key
    assert str(info.value) == f'{key} must be within [{low:g}, {high:g}], got {value!r}'
    build_configs({key: low})
    build_configs({key: high})


def test_every_numeric_setting_has_one_range():
    numeric = {k for k, v in DEFAULTS.items() if isinstance(v, float)}
    assert set(RANGES) == numeric
    assert all(low <= DEFAULTS[k] <= high for k, (low, high) in RANGES.items())


@pytest.mark.parametrize(
    'gains',
    [
        array.array('d', SM_GAINS_TABLE1),  # what rclpy hands over for a double array
        np.array(SM_GAINS_TABLE1),
        tuple(SM_GAINS_TABLE1),
        list(SM_GAINS_TABLE1),
        [0, 1, 0, 1, 0, 1, 0, 1, 0, 1, 0, 1],
    ],
    ids=['array', 'numpy', 'tuple', 'list', 'integers'],
)
def test_sm_gains_take_any_sequence_of_numbers(gains):
    engine, _ = build_configs({'sm_gains': gains, 'sm_exponents': array.array('d', [0.5] * 12)})
    assert engine.estimator.sm_gains == tuple(float(g) for g in gains)
    assert engine.estimator.sm_exponents == (0.5,) * 12


@pytest.mark.parametrize(
    ('value', 'reason'),
    [
        ('0.1, 0.2', "sm_gains must be a list of numbers, got '0.1, 0.2'"),
        ([0.1, 'x'] * 6, 'sm_gains must be a list of numbers'),
        ([True] * 12, 'sm_gains must be a list of numbers'),
        ({'a': 1.0}, 'sm_gains must be a list of numbers'),
        (0.1, 'sm_gains must be a list of numbers, got 0.1'),
        ([0.1], 'sm_gains needs 12 numbers, one per state, got 1'),
        (array.array('d', [0.1] * 13), 'sm_gains needs 12 numbers, one per state, got 13'),
        ([0.1] * 11 + [-1.0], 'sm_gains must be finite and >= 0, got -1.0 at index 11'),
    ],
)
def test_bad_sm_gains_are_refused_with_a_reason(value, reason):
    with pytest.raises(SettingsError) as info:
        build_configs({'sm_gains': value})
    assert str(info.value).startswith(reason)
    assert info.value.name == 'sm_gains'


@pytest.mark.parametrize(
    ('values', 'name', 'reason'),
    [
        ({'algorithm': 'foo'}, 'algorithm', "'foo' is not one of cloe, cloe_sm, cloe_iv"),
        ({'sm_exponents': [1.0] * 12}, 'sm_exponents', 'must lie in [0, 1), got 1.0 at index 0'),
        ({'l_min': 60.0}, 'l_min', 'must be at most l_max (50), got 60.0'),
        ({'id_highpass': 20.0}, 'id_highpass', 'must be below id_bandwidth (20), got 20.0'),
        ({'prediction_step': 6.0}, 'prediction_step',
         'must be at most prediction_horizon (5), got 6.0'),
        ({'output_ns': 'a b'}, 'output_ns', "'a b' is not a valid namespace"),
        ({'rate': 'fast'}, 'rate', "must be a number, got 'fast'"),
        ({'estimate_coupling': 1}, 'estimate_coupling', 'must be true or false, got 1'),
    ],
)  # fmt: skip
def test_refusals_name_the_setting(values, name, reason):
    """The node reports ``parameter '<name>': <reason>``; ``cloe infer`` ``<name> <reason>``."""
    with pytest.raises(SettingsError) as info:
        build_configs(values)
    assert (info.value.name, info.value.reason) == (name, reason)
    assert str(info.value) == f'{name} {reason}'


def test_a_file_names_itself_in_the_reason(tmp_path):
    path = tmp_path / 'inference.yaml'
    path.write_text('cloe_inference:\n  ros__parameters:\n    rate: 3000.0\n')
    with pytest.raises(SettingsError, match=r'inference.yaml: rate must be within \[1, 2000\]'):
        load_settings(path)


SHARDS = """\
/**:
  ros__parameters:
    algorithm: cloe_sm
    rate: 50.0
cloe_shard2:
  ros__parameters:
    rate: 20.0
"""


@pytest.mark.parametrize(
    ('text', 'node', 'expected'),
    [
        ('cloe_inference:\n  ros__parameters:\n    rate: 50.0\n', 'cloe_inference',
         {'rate': 50.0}),
        ('/cloe_inference:\n  ros__parameters:\n    rate: 50.0\n', 'cloe_inference',
         {'rate': 50.0}),
        ('/**:\n  ros__parameters:\n    rate: 50.0\n', 'cloe_inference', {'rate': 50.0}),
        ('/**:\n  ros__parameters:\n    rate: 50.0\n', 'cloe_shard1', {'rate': 50.0}),
        ('rate: 50.0\n', 'cloe_shard1', {'rate': 50.0}),
        ('cloe_shard1:\n  ros__parameters:\n    rate: 50.0\n', 'cloe_shard1', {'rate': 50.0}),
        ('cloe_shard1:\n  ros__parameters:\n    rate: 50.0\n', '/cloe_shard1', {'rate': 50.0}),
        ('/cloe_shard1:\n  ros__parameters:\n    rate: 50.0\n', 'cloe_shard1', {'rate': 50.0}),
        (SHARDS, 'cloe_shard2', {'algorithm': 'cloe_sm', 'rate': 20.0}),
        (SHARDS + 'quadrotor_sim:\n  ros__parameters:\n    scenario: hover\n', 'cloe_shard2',
         {'algorithm': 'cloe_sm', 'rate': 20.0}),
        (SHARDS, 'cloe_inference', {'algorithm': 'cloe_sm', 'rate': 50.0}),  # (/** alone, as ROS)
    ],
)  # fmt: skip
def test_a_node_reads_the_wildcard_section_then_its_own(tmp_path, text, node, expected):
    """As ROS gives a node named ``node`` its parameters: here ``/**`` comes first in the file,
    then its own section (with or without a leading ``/``), whose values win; other nodes'
    sections are ignored. (A ``/**`` written last wins: test_a_node_takes_the_sections_rclpy_
    gives_it.)"""
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    assert load_settings(path, node) == expected


#: Sections rclpy gives a node, beside its own and /**: nested namespaces, wildcards (/* one
#: name, /** any number, none included), in the file's order (a later /** overrides the node's
#: own section). Each case was checked against rclpy 7.1: a node created with --params-file on
#: the same text takes these values.
RCLPY_RULES = """\
/fleet/cloe_shard1:
  ros__parameters: {rate: 20.0, algorithm: cloe_sm, prediction_rate: 2.0}
fleet:
  cloe_shard1:
    ros__parameters: {rate: 25.0}
/**/cloe_shard1:
  ros__parameters: {prediction_rate: 4.0}
/*/cloe_shard2:
  ros__parameters: {rate: 40.0}
/**:
  ros__parameters: {algorithm: cloe_iv}
/fleet/*:
  ros__parameters: {rate: 10.0}
"""


@pytest.mark.parametrize(
    ('node', 'expected'),
    [
        ('/fleet/cloe_shard1', {'rate': 10.0, 'algorithm': 'cloe_iv', 'prediction_rate': 4.0}),
        ('cloe_shard1', {'algorithm': 'cloe_iv', 'prediction_rate': 4.0}),
        ('/a/b/cloe_shard1', {'algorithm': 'cloe_iv', 'prediction_rate': 4.0}),
        ('/fleet/cloe_shard2', {'rate': 10.0, 'algorithm': 'cloe_iv'}),
        ('/a/cloe_shard2', {'rate': 40.0, 'algorithm': 'cloe_iv'}),
        ('/a/b/cloe_shard2', {'algorithm': 'cloe_iv'}),
        ('cloe_inference', {'algorithm': 'cloe_iv'}),
    ],
)
def test_a_node_takes_the_sections_rclpy_gives_it(tmp_path, node, expected):
    """``--node`` names a node as rclpy gives it a parameter file: nested namespaces, ``/*``
    and ``/**`` patterns, every section that applies in the file's order (before: only ``/**``
    and the node's exact name, ``/**`` first whatever the order, and a nested section was an
    unknown setting, a wildcard one refused)."""
    path = tmp_path / 'params.yaml'
    path.write_text(RCLPY_RULES)
    assert load_settings(path, node) == expected


@pytest.mark.parametrize(
    ('text', 'reason'),
    [
        ('cloe_shard1:\n  ros__parameters:\n    rate: 50.0\n', '/cloe_shard1'),
        ('cloe_shard1:\n  ros__parameters:\n    rate: 50.0\nquadrotor_sim:\n  ros__parameters:\n'
         '    scenario: hover\n', '/cloe_shard1, /quadrotor_sim'),
        ('fleet:\n  cloe_inference:\n    ros__parameters:\n      rate: 50.0\n',
         '/fleet/cloe_inference'),  # (a namespace's node, not the root's)
    ],
)  # fmt: skip
def test_a_file_for_other_nodes_names_them_and_the_option(tmp_path, text, reason):
    """Sections keyed by other node names (a shard's), none by the node read and no ``/**``:
    the file is refused, naming the sections and ``--node`` (before: ``unknown setting(s):
    cloe_shard1``)."""
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    with pytest.raises(SettingsError) as info:
        load_settings(path)
    assert str(info.value) == (f'{path} has parameters for {reason}, not for /cloe_inference nor '
                               '/**: name the node to read with --node NAME')  # fmt: skip


def test_a_command_takes_the_files_settings_but_its_vehicles_and_its_own_overrides(tmp_path):
    """What ``cloe infer`` / ``report`` / ``evaluate`` run with: the file's settings for the node,
    not its ``vehicles`` (a command finds them in the bag), the command line's values where given;
    a bad value is refused before any work."""
    path = tmp_path / 'p.yaml'
    path.write_text('cloe_inference:\n  ros__parameters:\n    algorithm: cloe_sm\n    rate: 50.0\n'
                    "    vehicles: ['/uav1']\n")  # fmt: skip
    assert command_settings(path) == {'algorithm': 'cloe_sm', 'rate': 50.0}
    assert command_settings(path, algorithm='cloe_iv', rate=None) == {
        'algorithm': 'cloe_iv', 'rate': 50.0}  # fmt: skip
    assert command_settings(None, rate=200.0) == {'rate': 200.0}
    with pytest.raises(SettingsError, match='rate'):
        command_settings(None, rate=0.0)


#: Plain YAML values and how rcl types them, as a node given them in a parameter file (rclpy 7.1)
#: reported them: bool words, C's strtoll (hexadecimal, octal), strtod (exponents without a dot,
#: words, hexadecimal floats; out of range stays text), else text.
RCL_SCALARS = [
    ('5e1', 50.0), ('1.0e3', 1000.0), ('1e-3', 0.001), ('1_0.0', '1_0.0'), ('0x10', 16),
    ('010', 8), ('08', 8.0), ('1.', 1.0), ('.5', 0.5), ('+3', 3), ('+3.0', 3.0),
    ('-.inf', -math.inf), ('infinity', math.inf), ('yes', True), ('on', True), ('y', True),
    ('n', False), ('off', False), ('null', 'null'), ('~', '~'), ('1e400', '1e400'),
    ('1e-310', '1e-310'), ('99999999999999999999', 1e20), ('0x1p3', 8.0), ('1.5f', '1.5f'),
    ('0b11', '0b11'), ('2001-12-14', '2001-12-14'), ('9223372036854775807', 2**63 - 1),
    ('0x1p99999', '0x1p99999'), ('9' * 5000, '9' * 5000),  # (before: a traceback each)
]  # fmt: skip


@pytest.mark.parametrize(('text', 'expected'), RCL_SCALARS)
def test_a_value_is_typed_as_rcl_types_it(text, expected):
    """``cloe infer --config`` reads a value as the node does (before: PyYAML's YAML 1.1 rules,
    so that ``rate: 5e1`` or ``l_max: 1.0e3``, numbers to the node, were strings to
    ``cloe infer``, refused as 'must be a number', and ``1_0.0`` a number)."""
    value = param_sections.scalar(text)
    assert value == expected and type(value) is type(expected)
    quoted = param_sections.load(f'p: "{text}"\nq: !!str {text}\n')
    assert quoted == {'p': text, 'q': text}


def test_a_file_in_scientific_notation_is_read(tmp_path):
    path = tmp_path / 'params.yaml'
    path.write_text('cloe_inference:\n  ros__parameters:\n    rate: 5e1\n    l_max: 1.0e3\n')
    assert load_settings(path) == {'rate': 50.0, 'l_max': 1000.0}


def test_sections_rcl_stores_as_one_are_one_at_the_first_place(tmp_path):
    """Keys are names as written (``on`` is a node, not True); a key written twice, and two
    spellings rcl stores alike (``fleet: cloe_shard1:`` and ``fleet/cloe_shard1:``), are one
    section at the first one's place, so a ``/**`` between them wins (rclpy gives the node rate
    20 and prediction_rate 2: before, 30 and 2, and a repeated key lost the first's values)."""
    path = tmp_path / 'params.yaml'
    path.write_text('fleet:\n  cloe_shard1:\n    ros__parameters: {rate: 10.0}\n'
                    '/**:\n  ros__parameters: {rate: 20.0}\n'
                    'fleet/cloe_shard1:\n  ros__parameters: {rate: 30.0, prediction_rate: 2.0}\n'
                    'on:\n  ros__parameters: {rate: 40.0}\n'
                    'on:\n  ros__parameters: {prediction_rate: 4.0}\n')  # fmt: skip
    assert load_settings(path, '/fleet/cloe_shard1') == {'rate': 20.0, 'prediction_rate': 2.0}
    assert load_settings(path, 'on') == {'rate': 40.0, 'prediction_rate': 4.0}
    assert load_settings(path, 'True') == {'rate': 20.0}


@pytest.mark.parametrize(
    ('text', 'reason'),
    [
        ('a: &x {ros__parameters: {rate: 5.0}}\nb: *x\n', 'rcl does not support aliasing'),
        ('cloe_inference:\n  ros__parameters:\n', 'ros__parameters has no value'),
        ('cloe_inference:\n  ros__parameters:\n    rate:\n', 'parameter rate has no value'),
        ('cloe_inference:\n  ros__parameters:\n    vehicles: [1.0, 2]\n', 'an array mixing types'),
        ('/fleet/cloe_*:\n  ros__parameters: {rate: 5.0}\n', "accepts: 'cloe_*'"),
        ('cloe-x:\n  ros__parameters: {rate: 5.0}\n', "not a node name rcl accepts: 'cloe-x'"),
        ('1abc:\n  ros__parameters: {rate: 5.0}\n', "not a node name rcl accepts: '1abc'"),
        ('fleet/cloe_inference/:\n  ros__parameters: {rate: 5.0}\n', 'an empty name'),
        ('fleet:\n  /cloe_inference:\n    ros__parameters: {rate: 5.0}\n', 'starts with "/"'),
    ],
)  # fmt: skip
def test_what_rcl_refuses_is_refused_saying_why(tmp_path, text, reason):
    """A file the node cannot start with (rcl refuses it) is an error for ``cloe infer`` too,
    naming the file and the problem (before: read as if it were fine)."""
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    with pytest.raises(SettingsError) as info:
        load_settings(path)
    assert str(info.value).startswith(f'{path}') and reason in str(info.value), info.value


#: A file rcl reads in its own way, and the parameters a node /ns/n got from it (rclpy 7.1):
#: a tab between a value and its comment (libyaml's parser, as rcl's), documents merged, tags
#: ignored but !!str, block scalars typed like plain ones (``|`` keeps its newline), strtod's
#: nan(...), ``<<`` an ordinary name.
RCL_READING = """\
/ns/n:
  ros__parameters:
    a: 1\t# a tab before the comment
    s: a\tb
    t: !foo 5
    u: !!python/str 5
    v: |-
      5
    w: >-
      true
    x: |
      5
    y: nan(1)
    <<: {z: 1}
---
/ns/n:
  ros__parameters: {b: 2}
"""


def test_a_file_is_read_as_rcl_reads_it():
    """(before: refused for the tab, the second document and the unknown tags; the block
    scalars were strings, nan(1) a string, ``<<`` a merge key)"""
    got = param_sections.parameters_for(param_sections.load(RCL_READING), '/ns/n')[0]
    y = got.pop('y')
    assert math.isnan(y)
    assert got == {'a': 1, 's': 'a\tb', 't': 5, 'u': 5, 'v': 5, 'w': True, 'x': '5\n',
                   '<<.z': 1, 'b': 2}  # fmt: skip


def test_a_value_outside_the_sections_is_refused_as_the_node_refuses_it(tmp_path):
    """``cloe infer --config`` checks a node file's layout as the node's start-up does (before:
    a value beside ros__parameters was ignored by the one and refused by the other)."""
    path = tmp_path / 'params.yaml'
    path.write_text('cloe_inference:\n  rate: 5.0\n  ros__parameters: {rate: 50.0}\n')
    with pytest.raises(SettingsError) as info:
        load_settings(path)
    assert str(info.value) == (
        f'{path}: cloe_inference/rate is a value outside any ros__parameters (expected <node>: '
        'ros__parameters: {rate: ...})'
    )
