"""Inference settings from parameter values or YAML, shared by the node and ``cloe infer``.

The keys are the node's parameter names; the same YAML file configures both::

    cloe_inference:
      ros__parameters:
        algorithm: cloe_sm
        rate: 100.0

(a flat mapping of the same keys works too). As rclpy gives a parameter file to a node, the node
takes every section that applies to its name (its own, ``cloe_inference:`` or ``/cloe_inference:``;
``/**:`` for every node; wildcards and nested namespaces: :mod:`cloe_ros.io.param_sections`), in
the file's order, the later values winning; another node name (a node renamed ``cloe_shard1``, or
``/fleet/cloe_shard1`` in a namespace) is chosen by ``node_name``. Unknown keys are refused,
naming them. Names, defaults, ranges and which configuration field each key
fills are those of the table in :mod:`cloe_ros.settings`, which the node declares its parameters
from: a value the node refuses is refused here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from cloe_ros.core.anticipation import AnticipationConfig
from cloe_ros.core.engine import EngineConfig
from cloe_ros.core.estimator import ConfigError, EstimatorConfig
from cloe_ros.core.identifier import IdentifierConfig
from cloe_ros.core.prediction import PredictionConfig
from cloe_ros.io.outputs import OutputConfig, OutputConfigError
from cloe_ros.io.param_sections import (
    ParamFileError,
    check_layout,
    fully_qualified,
    load,
    parameters_for,
)
from cloe_ros.settings import ALGORITHMS, SETTINGS, engine_settings, node_settings

__all__ = ['ALGORITHMS', 'DEFAULTS', 'RANGES', 'SettingsError', 'build_configs', 'load_settings']

#: Parameters of the engine and outputs, with their defaults (node and CLI alike).
DEFAULTS: dict[str, Any] = {
    s.name: list(s.default) if isinstance(s.default, tuple) else s.default
    for s in engine_settings()
}
#: Closed range of every numeric setting of the engine and outputs.
RANGES: dict[str, tuple[float, float]] = {
    s.name: s.range for s in engine_settings() if s.range is not None
}
#: Node-only parameters a shared YAML file may also carry (ignored by ``cloe infer``).
NODE_ONLY = (*(s.name for s in node_settings()), 'use_sim_time')

#: Inference settings that cannot be used: every invalid setting is a :class:`ConfigError`
#: (``name`` is the setting at fault, ``reason`` the message after it); kept under this name for
#: its importers.
SettingsError = ConfigError


def build_configs(values: dict[str, Any]) -> tuple[EngineConfig, OutputConfig]:
    """Engine and output configs from parameter values (missing keys take the defaults); each
    value is checked as its setting says and fills the field the setting names."""
    unknown = sorted(set(values) - set(DEFAULTS) - set(NODE_ONLY))
    if unknown:
        msg = f'unknown setting(s): {", ".join(unknown)}; known: {", ".join(DEFAULTS)}'
        raise SettingsError(msg)
    fields: dict[str, dict[str, Any]] = {}
    for setting in engine_settings():
        value = values.get(setting.name, setting.default)
        fields.setdefault(setting.group, {})[setting.field] = setting.coerce(value)
    try:
        OutputConfig(fields['output']['output_ns'])
    except OutputConfigError as err:
        ns = fields['output']['output_ns']
        raise SettingsError(f'{ns!r} is not a valid namespace', 'output_ns') from err
    identifier = IdentifierConfig(**fields['identifier'])
    estimator = EstimatorConfig(identifier=identifier, **fields['estimator'])
    engine = EngineConfig(
        estimator=estimator,
        prediction=PredictionConfig(**fields['prediction']),
        anticipation=AnticipationConfig(**fields['anticipation']),
        **fields['engine'],
    )
    try:
        output = OutputConfig(**fields['output'])
    except ConfigError as err:  # (the checks above leave none)
        raise SettingsError(str(err)) from err
    return engine, output


def node_values(values: dict[str, Any]) -> dict[str, Any]:
    """The node's own settings from parameter values, checked (missing keys: the defaults)."""
    return {s.name: s.coerce(values.get(s.name, s.default)) for s in node_settings()}


#: The node name whose section of a parameter file ``cloe infer --config`` reads by default.
NODE_NAME = 'cloe_inference'


def load_settings(path: str | Path, node_name: str = NODE_NAME) -> dict[str, Any]:
    """Parameter values from a YAML file of ROS node sections (``<name>: ros__parameters: {...}``),
    or a flat mapping of them. Of node sections, those that apply to the node ``node_name`` (its
    fully qualified name; ``/`` first optional), in the file's order, as rclpy gives them to it
    (:func:`~cloe_ros.io.param_sections.parameters_for`). Raises :class:`SettingsError` for
    unreadable files, unknown keys and a file with sections for other nodes but none for
    ``node_name`` (naming them)."""
    path = Path(path)
    try:
        data = load(path.read_text())  # (as rcl reads it: cloe_ros.io.param_sections)
    except OSError as err:
        msg = f'cannot read {path}: {err.strerror or err}'
        raise SettingsError(msg) from err
    except yaml.YAMLError as err:
        mark = getattr(err, 'problem_mark', None)
        where = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
        problem = getattr(err, 'problem', None) or str(err).splitlines()[0]
        msg = f'{path} is not valid YAML{where}: {problem}'
        raise SettingsError(msg) from err
    if data is None:
        return {}
    if not isinstance(data, dict):
        msg = f'{path}: expected a mapping of parameter names to values'
        raise SettingsError(msg)
    try:
        data = _node_parameters(data, node_name, path)
    except ParamFileError as err:
        raise SettingsError(f'{path}: {err}') from err
    try:
        build_configs(data)  # refuse unknown keys and bad values now, naming the file
        node_values({k: v for k, v in data.items() if k in SETTINGS})
    except SettingsError as err:
        raise SettingsError(f'{path}: {err}') from err
    return data


def command_settings(
    path: str | Path | None, node_name: str = NODE_NAME, **overrides: Any
) -> dict[str, Any]:
    """The settings an offline command runs with: those the parameter file ``path`` gives the
    node ``node_name`` (none without a file) but ``vehicles`` (the command finds its vehicles in
    the bag), with the ``overrides`` that are not None (the command line's ``algorithm`` or
    ``rate``). Checked now: a bad value is one :class:`SettingsError`, before any work."""
    settings = load_settings(path, node_name) if path else {}
    settings = {k: v for k, v in settings.items() if k != 'vehicles'}
    settings.update({k: v for k, v in overrides.items() if v is not None})
    build_configs(settings)
    return settings


def _node_parameters(data: dict[str, Any], node_name: str, path: Path) -> dict[str, Any]:
    """The parameters of ``data`` (a parameter file's mapping) for the node ``node_name``: those
    of every section that applies to it, in the file's order, as rclpy gives them
    (:mod:`cloe_ros.io.param_sections`); ``data`` itself if it has no node section (a flat
    mapping). A file none of whose sections applies (only other nodes') is refused, naming
    them: it was meant for another node name."""
    node = fully_qualified(node_name)
    values, sections, taken = parameters_for(data, node)
    if not sections:
        return data
    check_layout(data)  # (a node's file: nothing outside its sections, as the node checks it)
    if not taken:
        msg = (f'{path} has parameters for {", ".join(sections)}, not for {node} nor /**: '
               'name the node to read with --node NAME')  # fmt: skip
        raise SettingsError(msg)
    return values
