"""Every setting of the inference engine and of ``cloe_inference``, written once.

Each :class:`Setting` holds its name, default, range or choices, description, whether it is
read-only on a running node and what changing it does. Everything else is derived from
:data:`SETTINGS`:

* the core's configuration dataclasses take their defaults from it (:func:`default`) and check
  their fields with it (:func:`check_fields`), naming the setting at fault;
* ``cloe_ros.io.config`` builds those dataclasses from parameter values or a YAML file
  (``cloe infer --config``), with the same checks;
* ``cloe_ros.ros.inference_node`` declares its parameters from it (type, range, read-only,
  description), validates changes with it and applies them as :attr:`Setting.on_change` says;
* ``scripts/make_settings_docs.py`` writes the README's parameter table and
  ``config/inference.yaml`` from it, and tests check both against it.

This module imports nothing of the package but its errors (no numpy, no ROS), so that the core can
import it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Set
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

from cloe_ros.errors import ConfigError

__all__ = [
    'ALGORITHMS',
    'SETTINGS',
    'SM_EXPONENTS',
    'SM_GAINS_TABLE1',
    'Setting',
    'check_fields',
    'default',
    'engine_settings',
    'node_settings',
]

#: Number of states, in the order of the model (``cloe_ros.core.model.N_STATES``).
N_STATES = 12
#: The estimator algorithms: the paper's two, and CLOE-SM with the IV identifier.
ALGORITHMS = ('cloe', 'cloe_sm', 'cloe_iv')
#: Sliding-mode gains alpha of the paper's Table 1, per state (x-theta and y-phi chains: 0.12,
#: 0.18, 0.24, 0.30; psi and z: 0.24, 0.30).
SM_GAINS_TABLE1 = (0.12, 0.18, 0.24, 0.30, 0.12, 0.18, 0.24, 0.30, 0.24, 0.30, 0.24, 0.30)
#: Sliding-mode exponents p, decreasing along each chain (docs/method.md), per state.
SM_EXPONENTS = (0.75, 0.5, 0.25, 0.0, 0.75, 0.5, 0.25, 0.0, 0.5, 0.0, 0.5, 0.0)

#: What a change on a running node does (:attr:`Setting.on_change`).
AT_ONCE = 'at_once'  # applies at the next step; state and identified model kept
RESTARTS = 'restarts'  # restarts the estimators: the identified models are forgotten
RESTARTS_CLOE_IV = 'restarts_cloe_iv'  # with cloe_iv, restarts them; otherwise at once
NEXT_START = 'next_start'  # applies from the next (re)start of an estimator


@dataclass(frozen=True)
class Setting:
    """One setting.

    Attributes:
        name: Parameter name of the node and key of ``cloe infer --config``.
        default: Default value; its type is the setting's (float, int, bool, str, a tuple of
            ``N_STATES`` floats, or a list of strings).
        description: What it is, with units; the node's ``ParameterDescriptor.description``.
        range: Closed range of a number.
        choices: The values a string may take.
        items: Per-state values: the closed range of each value, ``high`` excluded when
            ``open_high``.
        open_high: See ``items``.
        read_only: Fixed once the node has started.
        on_change: What a change on a running node does (``AT_ONCE``, ``RESTARTS``,
            ``RESTARTS_CLOE_IV``, ``NEXT_START``); unused when read-only.
        target: ``'<config>.<field>'`` the setting fills: ``engine`` (EngineConfig),
            ``estimator`` (EstimatorConfig), ``identifier`` (IdentifierConfig), ``prediction``
            (PredictionConfig), ``anticipation`` (AnticipationConfig), ``output``
            (OutputConfig); empty for the node's own settings, which ``cloe infer`` ignores.

    """

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()
    items: tuple[float, float] | None = None
    open_high: bool = False
    read_only: bool = False
    on_change: str = AT_ONCE
    target: str = ''

    @property
    def kind(self) -> type:
        """``bool``, ``int``, ``float``, ``str``, ``tuple`` (per-state floats) or ``list``
        (strings)."""
        return type(self.default)

    @property
    def group(self) -> str:
        return self.target.partition('.')[0]

    @property
    def field(self) -> str:
        return self.target.partition('.')[2]

    @property
    def node_only(self) -> bool:
        return not self.target

    def coerce(self, value: Any) -> Any:
        """``value`` (from YAML or a ROS parameter) as this setting's type, checked; raises
        :class:`ConfigError` naming the setting."""
        kind = self.kind
        if kind is bool:
            if not isinstance(value, bool):
                raise ConfigError(f'must be true or false, got {value!r}', self.name)
        elif kind is float:
            if not _is_number(value):
                raise ConfigError(f'must be a number, got {value!r}', self.name)
            value = float(value)
        elif kind is int:
            if not (isinstance(value, Integral) and not isinstance(value, bool)):
                raise ConfigError(f'must be an integer, got {value!r}', self.name)
            value = int(value)
        elif kind is str:
            if not isinstance(value, str):
                raise ConfigError(f'must be a string, got {value!r}', self.name)
        elif kind is tuple:
            items = _sequence(value)
            if items is None or not all(_is_number(x) for x in items):
                raise ConfigError(f'must be a list of numbers, got {value!r}', self.name)
            value = tuple(float(x) for x in items)
        elif kind is list:
            items = _sequence(value)
            if items is None or not all(isinstance(x, str) for x in items):
                raise ConfigError(f'must be a list of strings, got {value!r}', self.name)
            value = list(items)
        self.check(value)
        return value

    def check(self, value: Any) -> None:
        """Refuse, with :class:`ConfigError` naming the setting, a value of the right type out
        of range, not among the choices, or with the wrong number of per-state values."""
        if self.range is not None:
            low, high = self.range
            if not (math.isfinite(value) and low <= value <= high):
                raise ConfigError(f'must be within [{low:g}, {high:g}], got {value!r}', self.name)
        if self.choices and value not in self.choices:
            raise ConfigError(f'{value!r} is not one of {", ".join(self.choices)}', self.name)
        if self.items is not None:
            if len(value) != N_STATES:
                raise ConfigError(
                    f'needs {N_STATES} numbers, one per state, got {len(value)}', self.name
                )
            low, high = self.items
            for k, x in enumerate(value):
                if not (math.isfinite(x) and low <= x and (x < high if self.open_high
                                                           else x <= high)):  # fmt: skip
                    raise ConfigError(f'{self.items_text} got {x!r} at index {k}', self.name)

    @property
    def items_text(self) -> str:
        """The per-state constraint in words, ending with a comma: ``must lie in [0, 1),``."""
        low, high = self.items
        if math.isinf(high):
            return f'must be finite and >= {low:g},'
        return f'must lie in [{low:g}, {high:g}{")" if self.open_high else "]"},'

    def constraints(self) -> str:
        """The constraint in words, for ``ParameterDescriptor.additional_constraints`` (ranges
        have their own fields there)."""
        if self.choices:
            return 'one of ' + ', '.join(self.choices)
        if self.items is not None:
            low, high = self.items
            if math.isinf(high):
                return f'{N_STATES} values >= {low:g}'
            return f'{N_STATES} values in [{low:g}, {high:g}{")" if self.open_high else "]"}'
        return ''

    def change_note(self) -> str:
        """What a runtime change does, in words ('' when it simply applies, or read-only)."""
        if self.read_only:
            return ''
        return {
            RESTARTS: 'changing it restarts the estimators',
            RESTARTS_CLOE_IV: 'with cloe_iv, changing it restarts the estimators',
            NEXT_START: 'a change applies from the next (re)start',
        }.get(self.on_change, '')

    def full_description(self) -> str:
        """The description, with what a change does: the node's parameter description."""
        note = self.change_note()
        return f'{self.description}; {note}' if note else self.description


def _is_number(value: Any) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool)


def _sequence(value: Any) -> list | None:
    """Any sequence as a list (rclpy hands arrays over as ``array.array``, YAML as lists); None
    for a string, a mapping, a set or a scalar."""
    if isinstance(value, Iterable) and not isinstance(value, (str, bytes, Mapping, Set)):
        return list(value)
    return None


_RO = {'read_only': True}

#: Every setting, in the order the README and config/inference.yaml list them.
SETTINGS: dict[str, Setting] = {s.name: s for s in (
    # -- which vehicles ------------------------------------------------------------------------
    Setting('vehicles', [], 'vehicle namespaces, e.g. [/uav1, /uav2]; empty: one vehicle, topics '
            'relative to the node namespace (unless discover)', **_RO),
    Setting('discover', False, 'also infer every namespace that publishes both <ns>/odom and '
            '<ns>/reference, including vehicles that appear later (the ROS graph is polled '
            'every discovery_period)', **_RO),
    Setting('shard_index', 0, 'this node infers the vehicles whose namespace hashes to it: '
            'crc32(namespace) mod shard_count == shard_index (listed and discovered alike)',
            range=(0, 9999), **_RO),
    Setting('shard_count', 1, 'number of nodes sharing the vehicles (see shard_index); 1: all '
            'vehicles', range=(1, 10000), **_RO),
    Setting('discovery_period', 1.0, 'period of the ROS graph poll (discovery, and the check that '
            'every vehicle has publishers), s of wall time', range=(0.05, 60.0), **_RO),
    Setting('publisher_timeout', 5.0, 'a vehicle without a publisher of odom or reference (of its '
            'type) this long after the start (or after its publishers left) gets a warning, s of '
            'wall time',
            range=(0.1, 3600.0), **_RO),
    # -- the estimator --------------------------------------------------------------------------
    Setting('algorithm', 'cloe_iv', 'estimator: cloe, cloe_sm or cloe_iv (cloe and cloe_sm as the '
            'paper states them; cloe_iv identifies with instrumental variables)',
            choices=ALGORITHMS, on_change=RESTARTS, target='estimator.algorithm'),
    Setting('rate', 100.0, 'estimator steps per second of message time, Hz', range=(1.0, 2000.0),
            on_change=RESTARTS, target='engine.rate'),
    Setting('gamma_theta', 400.0, 'cloe, cloe_sm: identifier gain Gamma (paper: 400)',
            range=(0.0, 1e6), target='estimator.gamma_theta'),
    Setting('gamma_l', 400.0, 'adaptive observer-gain rate gamma (paper: 400)', range=(0.0, 1e6),
            target='estimator.gamma_l'),
    Setting('l_initial', 0.0, 'initial observer gain L(0), 1/s (cloe_iv: at least l_min)',
            range=(0.0, 1e4), on_change=NEXT_START, target='estimator.l_initial'),
    Setting('sm_gains', SM_GAINS_TABLE1, 'sliding-mode gains alpha, one per state (paper Table '
            '1)', items=(0.0, math.inf), target='estimator.sm_gains'),
    Setting('sm_exponents', SM_EXPONENTS, 'sliding-mode exponents p, one per state',
            items=(0.0, 1.0), open_high=True, target='estimator.sm_exponents'),
    Setting('reference_timeout', 0.25, 'odometry lead (s) after which a missing newer reference '
            'is held', range=(0.0, 60.0), target='engine.reference_timeout'),
    Setting('reference_wait', 'due', 'when a step waits for a newer reference: due, only once '
            'the next reference is due (0.9 of the reference interval after the last; one that '
            'comes earlier applies from the step after it arrives); stamps, until a reference '
            'at or after the step has come (the estimates depend on the stamps alone, at up to '
            'one reference interval of latency)', choices=('due', 'stamps'),
            target='engine.reference_wait'),
    Setting('max_gap', 1.0, 'odometry gap (s) treated as a time jump: the estimator '
            're-initialises', range=(0.001, 3600.0), target='engine.max_gap'),
    Setting('world_frame', '', 'required header.frame_id of odom and reference; empty: the first '
            'one seen', target='engine.world_frame', **_RO),
    Setting('output_ns', 'cloe', 'namespace of the outputs under each vehicle namespace',
            target='output.output_ns', **_RO),
    Setting('parameters_rate', 10.0, 'parameters messages per second of message time, Hz',
            range=(0.01, 1000.0), target='output.parameters_rate'),
    # -- anticipation ---------------------------------------------------------------------------
    Setting('prediction_horizon', 5.0, 'anticipated path length, s (0: no predictions)',
            range=(0.0, 120.0), target='prediction.horizon', **_RO),
    Setting('prediction_step', 0.1, 'spacing of the predicted poses, s', range=(0.001, 10.0),
            target='prediction.step', **_RO),
    Setting('prediction_rate', 5.0, 'predictions per second of message time, Hz',
            range=(0.01, 1000.0), target='prediction.rate', **_RO),
    Setting('prediction_phase', 'aligned', 'when in each 1 / prediction_rate the predictions '
            'fall: aligned, at the first grid step of each period of message time, for every '
            'vehicle alike; spread, each vehicle at its own grid step of the period (a hash of '
            'its namespace), so that the predictions of a swarm on one clock do not all fall on '
            'one step and delay its states (no shift when prediction_rate >= rate)',
            choices=('aligned', 'spread'),
            target='prediction.phase', **_RO),
    Setting('prediction_disturbance_time', 0.5, 'window of the recent model-error fit and its '
            'fading time over the horizon, s (0: steady-state offsets only)', range=(0.0, 10.0),
            target='prediction.disturbance_time', **_RO),
    Setting('prediction_intent', True, 'without a plan, predict where the reference goes from its '
            'recent past (else: held)', target='anticipation.intent', **_RO),
    Setting('prediction_guard', True, 'publish, per horizon, the combination of the closed loop '
            'and model-free predictors that did best recently (else: the closed loop alone)',
            target='anticipation.guard', **_RO),
    Setting('prediction_coverage', 0.95, 'probability the published prediction radius is meant '
            'to hold', range=(0.5, 0.999), target='anticipation.coverage', **_RO),
    Setting('reference_trust', True, 'check whether the vehicle tracks each reference channel; a '
            'channel it does not track is replaced by the reference its motion implies (else: '
            'always trusted)', target='anticipation.trust', **_RO),
    Setting('reference_trust_ratio', 3.0, 'a reference channel is not tracked when the model '
            'driven by it misses the last second by more than this many times constant velocity '
            '(and by more than reference_trust_floor)', range=(1.0, 100.0),
            target='anticipation.trust_ratio', **_RO),
    Setting('reference_trust_floor', 0.3, 'the least miss of the model driven by a reference '
            'channel over the last second that makes it not tracked, m (rad for yaw)',
            range=(0.0, 1e3), target='anticipation.trust_floor', **_RO),
    # -- cloe_iv --------------------------------------------------------------------------------
    Setting('l_leak', 0.1, 'cloe_iv: leakage of the observer gain L, 1/s', range=(0.0, 1e3),
            target='estimator.l_leak'),
    Setting('gamma_d', 400.0, "cloe_iv: rate of the observer's model-error state on the unknown "
            'rows, 1/s^2', range=(0.0, 1e6), target='estimator.gamma_d'),
    Setting('l_min', 5.0, 'cloe_iv: lower bound of L, 1/s', range=(0.0, 1e6),
            target='estimator.l_min'),
    Setting('l_max', 50.0, 'cloe_iv: upper bound of L, 1/s', range=(1e-6, 1e6),
            target='estimator.l_max'),
    Setting('id_bandwidth', 20.0, "cloe_iv: identifier's filter bandwidth, rad/s",
            range=(0.1, 1000.0), on_change=RESTARTS_CLOE_IV, target='identifier.bandwidth'),
    Setting('id_highpass', 0.2, "cloe_iv: identifier's high-pass corner, rad/s",
            range=(0.001, 100.0), on_change=RESTARTS_CLOE_IV, target='identifier.highpass'),
    Setting('id_window', 60.0, 'cloe_iv: forgetting time constant of the estimate, s',
            range=(0.1, 1e6), on_change=RESTARTS_CLOE_IV, target='identifier.window'),
    Setting('id_excitation_window', 10.0, 'cloe_iv: time constant of the excitation measure, s',
            range=(0.1, 1e6), on_change=RESTARTS_CLOE_IV, target='identifier.excitation_window'),
    Setting('id_excitation_threshold', 0.02, 'cloe_iv: smallest canonical correlation counted as '
            'excited', range=(0.0, 1.0), on_change=RESTARTS_CLOE_IV,
            target='identifier.excitation_threshold'),
    Setting('estimate_coupling', True, 'cloe_iv: identify the tilt couplings (the paper fixes '
            'them at +-g)', on_change=RESTARTS_CLOE_IV, target='identifier.estimate_coupling'),
    Setting('ground_altitude', 0.05, 'cloe_iv: identification pauses while the commanded altitude '
            'is at or below this, m (below every commanded altitude: never); predictions then do '
            'not rely on the reference', range=(-1e3, 1e3), target='estimator.ground_altitude'),
    # -- the node -------------------------------------------------------------------------------
    Setting('diagnostics_period', 1.0, '/diagnostics period, s', range=(0.05, 60.0), **_RO),
    Setting('batch_period', 0.005, 'the vehicles with new input are stepped together, one '
            'batched estimator call per grid step, as soon as every vehicle has new input and '
            'at the latest 1.5 batch_period, s of wall time, after the first input; 0: each '
            'vehicle at each of its messages, alone', range=(0.0, 0.1), **_RO),
    Setting('qos_reliability', 'reliable', 'QoS reliability of the subscriptions: reliable or '
            'best_effort', choices=('reliable', 'best_effort'), **_RO),
    Setting('qos_depth', 1000, 'QoS history depth of the subscriptions and of the output '
            'publishers (10 s of 100 Hz odometry: a node starved of CPU for a moment loses '
            'nothing)', range=(1, 100000), **_RO),
)}  # fmt: skip


def engine_settings() -> list[Setting]:
    """The settings of the engine and outputs (what ``cloe infer --config`` takes)."""
    return [s for s in SETTINGS.values() if not s.node_only]


def node_settings() -> list[Setting]:
    """The node's own settings (``cloe infer`` ignores them)."""
    return [s for s in SETTINGS.values() if s.node_only]


def default(name: str) -> Any:
    """The default of setting ``name`` (a dataclass field default: immutable)."""
    value = SETTINGS[name].default
    return tuple(value) if isinstance(value, list) else value


_BY_GROUP: dict[str, list[Setting]] = {}
for _s in SETTINGS.values():
    if _s.target:
        _BY_GROUP.setdefault(_s.group, []).append(_s)


def check_fields(config: Any, group: str) -> None:
    """Check every field of ``config`` (a configuration dataclass) that a setting of ``group``
    fills, as that setting does; :class:`ConfigError` names the setting."""
    for setting in _BY_GROUP[group]:
        setting.check(getattr(config, setting.field))
