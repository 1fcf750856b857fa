"""Inference settings from parameter values or YAML, shared by the node and ``cloe infer``.

The keys are the node's parameter names; the same YAML file configures both::

    cloe_inference:
      ros__parameters:
        algorithm: cloe_sm
        rate: 100.0

(a flat mapping of the same keys works too). Unknown keys are refused, naming them. The ranges
(:data:`RANGES`) are the node's too: it declares its parameters with them, so a value the node
refuses is refused here.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Set
from numbers import Real
from pathlib import Path
from typing import Any

import yaml

from cloe_ros.core.anticipation import AnticipationConfig
from cloe_ros.core.engine import EngineConfig
from cloe_ros.core.estimator import (
    ALGORITHMS,
    SM_EXPONENTS,
    SM_GAINS_TABLE1,
    ConfigError,
    EstimatorConfig,
)
from cloe_ros.core.identifier import IdentifierConfig
from cloe_ros.core.model import N_STATES
from cloe_ros.core.prediction import PredictionConfig
from cloe_ros.io.outputs import OutputConfig, OutputConfigError

__all__ = ['ALGORITHMS', 'DEFAULTS', 'RANGES', 'SettingsError', 'build_configs', 'load_settings']

#: Parameters of the engine and outputs, with their defaults (node and CLI alike).
DEFAULTS: dict[str, Any] = {
    'algorithm': 'cloe_iv',
    'rate': 100.0,
    'gamma_theta': 400.0,
    'gamma_l': 400.0,
    'l_initial': 0.0,
    'sm_gains': list(SM_GAINS_TABLE1),
    'sm_exponents': list(SM_EXPONENTS),
    'reference_timeout': 0.25,
    'max_gap': 1.0,
    'world_frame': '',
    'output_ns': 'cloe',
    'parameters_rate': 10.0,
    'prediction_horizon': 5.0,
    'prediction_step': 0.1,
    'prediction_rate': 5.0,
    'prediction_disturbance_time': 0.5,
    'l_leak': 0.1,
    'gamma_d': 400.0,
    'l_min': 5.0,
    'l_max': 50.0,
    'id_bandwidth': 20.0,
    'id_highpass': 0.2,
    'id_window': 60.0,
    'id_excitation_window': 10.0,
    'id_excitation_threshold': 0.02,
    'estimate_coupling': True,
    'ground_altitude': 0.05,
    'prediction_intent': True,
    'prediction_guard': True,
    'prediction_coverage': 0.95,
    'reference_trust': True,
    'reference_trust_ratio': 3.0,
    'reference_trust_floor': 0.3,
}
#: Closed range of every numeric setting: the node's declared range and what ``cloe infer`` takes.
RANGES: dict[str, tuple[float, float]] = {
    'rate': (1.0, 2000.0),
    'gamma_theta': (0.0, 1e6),
    'gamma_l': (0.0, 1e6),
    'l_initial': (0.0, 1e4),
    'reference_timeout': (0.0, 60.0),
    'max_gap': (0.001, 3600.0),
    'parameters_rate': (0.01, 1000.0),
    'prediction_horizon': (0.0, 120.0),
    'prediction_step': (0.001, 10.0),
    'prediction_rate': (0.01, 1000.0),
    'prediction_disturbance_time': (0.0, 10.0),
    'l_leak': (0.0, 1e3),
    'gamma_d': (0.0, 1e6),
    'l_min': (0.0, 1e6),
    'l_max': (1e-6, 1e6),
    'id_bandwidth': (0.1, 1000.0),
    'id_highpass': (0.001, 100.0),
    'id_window': (0.1, 1e6),
    'id_excitation_window': (0.1, 1e6),
    'id_excitation_threshold': (0.0, 1.0),
    'ground_altitude': (-1e3, 1e3),
    'prediction_coverage': (0.5, 0.999),
    'reference_trust_ratio': (1.0, 100.0),
    'reference_trust_floor': (0.0, 1e3),
}
#: Settings that are true or false.
FLAGS = ('estimate_coupling', 'prediction_intent', 'prediction_guard', 'reference_trust')
#: Node-only parameters a shared YAML file may also carry (ignored by ``cloe infer``).
NODE_ONLY = ('vehicles', 'diagnostics_period', 'qos_reliability', 'qos_depth', 'use_sim_time')


#: Inference settings that cannot be used: every invalid setting is a :class:`ConfigError`
#: (``name`` is the setting at fault, ``reason`` the message after it); kept under this name for
#: its importers.
SettingsError = ConfigError


def build_configs(values: dict[str, Any]) -> tuple[EngineConfig, OutputConfig]:
    """Engine and output configs from parameter values (missing keys take the defaults)."""
    unknown = sorted(set(values) - set(DEFAULTS) - set(NODE_ONLY))
    if unknown:
        msg = f'unknown setting(s): {", ".join(unknown)}; known: {", ".join(DEFAULTS)}'
        raise SettingsError(msg)
    v = {**DEFAULTS, **values}
    if v['algorithm'] not in ALGORITHMS:
        reason = f'{v["algorithm"]!r} is not one of {", ".join(ALGORITHMS)}'
        raise SettingsError(reason, 'algorithm')
    for flag in FLAGS:
        if not isinstance(v[flag], bool):
            raise SettingsError(f'must be true or false, got {v[flag]!r}', flag)
    n = {name: _number(v, name) for name in RANGES}
    gains, exponents = _numbers(v, 'sm_gains'), _numbers(v, 'sm_exponents')
    for k, g in enumerate(gains):
        if not (math.isfinite(g) and g >= 0):
            raise SettingsError(f'must be finite and >= 0, got {g!r} at index {k}', 'sm_gains')
    for k, p in enumerate(exponents):
        if not 0.0 <= p < 1.0:
            raise SettingsError(f'must lie in [0, 1), got {p!r} at index {k}', 'sm_exponents')
    _below(n, 'l_min', 'l_max', strict=False)
    _below(n, 'id_highpass', 'id_bandwidth', strict=True)
    if n['prediction_horizon']:
        _below(n, 'prediction_step', 'prediction_horizon', strict=False)
    try:
        OutputConfig(str(v['output_ns']))
    except OutputConfigError as err:
        raise SettingsError(f'{v["output_ns"]!r} is not a valid namespace', 'output_ns') from err
    try:
        identifier = IdentifierConfig(
            bandwidth=n['id_bandwidth'],
            highpass=n['id_highpass'],
            window=n['id_window'],
            excitation_window=n['id_excitation_window'],
            excitation_threshold=n['id_excitation_threshold'],
            estimate_coupling=v['estimate_coupling'],
        )
        estimator = EstimatorConfig(
            algorithm=v['algorithm'],
            gamma_theta=n['gamma_theta'],
            gamma_l=n['gamma_l'],
            l_initial=n['l_initial'],
            sm_gains=tuple(gains),
            sm_exponents=tuple(exponents),
            l_leak=n['l_leak'],
            gamma_d=n['gamma_d'],
            l_min=n['l_min'],
            l_max=n['l_max'],
            identifier=identifier,
            ground_altitude=n['ground_altitude'],
        )
        engine = EngineConfig(
            rate=n['rate'],
            estimator=estimator,
            reference_timeout=n['reference_timeout'],
            max_gap=n['max_gap'],
            world_frame=str(v['world_frame']),
            prediction=PredictionConfig(
                horizon=n['prediction_horizon'],
                step=n['prediction_step'],
                rate=n['prediction_rate'],
                disturbance_time=n['prediction_disturbance_time'],
            ),
            anticipation=AnticipationConfig(
                intent=v['prediction_intent'],
                guard=v['prediction_guard'],
                trust=v['reference_trust'],
                coverage=n['prediction_coverage'],
                trust_ratio=n['reference_trust_ratio'],
                trust_floor=n['reference_trust_floor'],
            ),
        )
        output = OutputConfig(str(v['output_ns']), n['parameters_rate'])
    except ConfigError as err:  # (the checks above leave none of these)
        raise SettingsError(str(err)) from err
    return engine, output


def _is_number(value: Any) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool)


def _number(values: dict, name: str) -> float:
    """``values[name]`` as a float within ``RANGES[name]``."""
    value = values[name]
    if not _is_number(value):
        raise SettingsError(f'must be a number, got {value!r}', name)
    value = float(value)
    low, high = RANGES[name]
    if not (math.isfinite(value) and low <= value <= high):
        raise SettingsError(f'must be within [{low:g}, {high:g}], got {value!r}', name)
    return value


def _numbers(values: dict, name: str) -> list[float]:
    """``values[name]``, one number per state, as floats. Any sequence of numbers will do: rclpy
    hands double arrays over as ``array.array``, YAML gives lists."""
    value = values[name]
    items = None
    if isinstance(value, Iterable) and not isinstance(value, (str, bytes, Mapping, Set)):
        items = list(value)
    if items is None or not all(_is_number(x) for x in items):
        raise SettingsError(f'must be a list of numbers, got {value!r}', name)
    out = [float(x) for x in items]
    if len(out) != N_STATES:
        raise SettingsError(f'needs {N_STATES} numbers, one per state, got {len(out)}', name)
    return out


def _below(n: dict[str, float], name: str, bound: str, strict: bool) -> None:
    if n[name] > n[bound] or (strict and n[name] == n[bound]):
        relation = 'below' if strict else 'at most'
        raise SettingsError(f'must be {relation} {bound} ({n[bound]:g}), got {n[name]!r}', name)


def load_settings(path: str | Path, node_name: str = 'cloe_inference') -> dict[str, Any]:
    """Parameter values from a YAML file: ``<node_name>: ros__parameters: {...}``, ``/**:`` or a
    flat mapping. Raises :class:`SettingsError` for unreadable files and unknown keys."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
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
    for key in (node_name, f'/{node_name}', '/**'):
        section = data.get(key)
        if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
            data = section['ros__parameters']
            break
    try:
        build_configs(data)  # refuse unknown keys and bad values now, naming the file
    except SettingsError as err:
        raise SettingsError(f'{path}: {err}') from err
    return data
