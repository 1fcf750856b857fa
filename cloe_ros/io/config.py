"""Inference settings from parameter values or YAML, shared by the node and ``cloe infer``.

The keys are the node's parameter names; the same YAML file configures both::

    cloe_inference:
      ros__parameters:
        algorithm: cloe_sm
        rate: 100.0

(a flat mapping of the same keys works too). Unknown keys are refused, naming them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from cloe_ros.core.engine import EngineConfig
from cloe_ros.core.estimator import (
    ALGORITHMS,
    SM_EXPONENTS,
    SM_GAINS_TABLE1,
    ConfigError,
    EstimatorConfig,
)
from cloe_ros.core.identifier import IdentifierConfig
from cloe_ros.core.prediction import PredictionConfig
from cloe_ros.errors import CloeError
from cloe_ros.io.outputs import OutputConfig, OutputConfigError

__all__ = ['ALGORITHMS', 'DEFAULTS', 'SettingsError', 'build_configs', 'load_settings']

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
}
#: Node-only parameters a shared YAML file may also carry (ignored by ``cloe infer``).
NODE_ONLY = ('vehicles', 'diagnostics_period', 'qos_reliability', 'qos_depth', 'use_sim_time')


class SettingsError(CloeError, ValueError):
    """Inference settings that cannot be used; the message says which and why."""


def build_configs(values: dict[str, Any]) -> tuple[EngineConfig, OutputConfig]:
    """Engine and output configs from parameter values (missing keys take the defaults)."""
    unknown = sorted(set(values) - set(DEFAULTS) - set(NODE_ONLY))
    if unknown:
        msg = f'unknown setting(s): {", ".join(unknown)}; known: {", ".join(DEFAULTS)}'
        raise SettingsError(msg)
    v = {**DEFAULTS, **values}
    if v['algorithm'] not in ALGORITHMS:
        msg = f'algorithm {v["algorithm"]!r} is not one of {", ".join(ALGORITHMS)}'
        raise SettingsError(msg)
    if not isinstance(v['estimate_coupling'], bool):
        msg = f'estimate_coupling must be true or false, got {v["estimate_coupling"]!r}'
        raise SettingsError(msg)
    try:
        identifier = IdentifierConfig(
            bandwidth=_number(v, 'id_bandwidth'),
            highpass=_number(v, 'id_highpass'),
            window=_number(v, 'id_window'),
            excitation_window=_number(v, 'id_excitation_window'),
            excitation_threshold=_number(v, 'id_excitation_threshold'),
            estimate_coupling=v['estimate_coupling'],
        )
        estimator = EstimatorConfig(
            algorithm=v['algorithm'],
            gamma_theta=_number(v, 'gamma_theta'),
            gamma_l=_number(v, 'gamma_l'),
            l_initial=_number(v, 'l_initial'),
            sm_gains=tuple(_numbers(v, 'sm_gains')),
            sm_exponents=tuple(_numbers(v, 'sm_exponents')),
            l_leak=_number(v, 'l_leak'),
            gamma_d=_number(v, 'gamma_d'),
            l_min=_number(v, 'l_min'),
            l_max=_number(v, 'l_max'),
            identifier=identifier,
            ground_altitude=_number(v, 'ground_altitude'),
        )
        engine = EngineConfig(
            rate=_number(v, 'rate'),
            estimator=estimator,
            reference_timeout=_number(v, 'reference_timeout'),
            max_gap=_number(v, 'max_gap'),
            world_frame=str(v['world_frame']),
            prediction=PredictionConfig(
                horizon=_number(v, 'prediction_horizon'),
                step=_number(v, 'prediction_step'),
                rate=_number(v, 'prediction_rate'),
                disturbance_time=_number(v, 'prediction_disturbance_time'),
            ),
        )
        output = OutputConfig(str(v['output_ns']), _number(v, 'parameters_rate'))
    except (ConfigError, OutputConfigError) as err:
        raise SettingsError(str(err)) from err
    return engine, output


def _number(values: dict, name: str) -> float:
    value = values[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        msg = f'{name} must be a number, got {value!r}'
        raise SettingsError(msg)
    return float(value)


def _numbers(values: dict, name: str) -> list[float]:
    value = values[name]
    if not isinstance(value, (list, tuple)):
        msg = f'{name} must be a list of numbers, got {value!r}'
        raise SettingsError(msg)
    return [_number({name: x}, name) for x in value]


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
