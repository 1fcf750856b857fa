"""What every node of the package shares: start/stop, parameter validation helpers, QoS, names.

The only modules that import rclpy are under ``cloe_ros.ros``.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import os
import re
import signal
import sys
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import rclpy
import yaml
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.task import Future

from cloe_ros.interrupts import uninterrupted
from cloe_ros.io.param_sections import (
    ParamFileError,
    applies,
    brief,
    check_layout,
    load,
    node_sections,
)
from cloe_ros.ros.errors import ParameterError, StartupError
from cloe_ros.threads import limit_blas_threads

NS = 1_000_000_000


def destroyed_if_init_fails(init: Callable) -> Callable:
    """For a node's ``__init__``: a node whose construction fails (a refused parameter, a bag
    that does not open) is destroyed before the error goes on, so that it does not stay in the
    ROS graph of its context, where a process that goes on (a test, an in-process user) would
    still see a node of that name. Its own ``destroy_node`` runs first (it may hold a file or a
    thread); if that fails on the half-made node, rclpy's does."""

    @functools.wraps(init)
    def wrapper(self: Node, *args, **kwargs) -> None:
        try:
            init(self, *args, **kwargs)
        except BaseException:
            try:
                self.destroy_node()
            except Exception:
                with contextlib.suppress(Exception):  # (not made far enough to be destroyed)
                    Node.destroy_node(self)
            raise

    return wrapper


def spin_while(executor, keep_going: Callable[[], bool], period: float) -> None:
    """Spin ``executor`` while ``keep_going()``, asked every ``period`` s: each call of
    ``spin_until_future_complete``, of a future that never completes (a new one each time: each
    call adds a callback to it), runs every callback due in ``period``. ``spin_once`` runs one
    callback per call, and a loop of it with a check between calls cost about as much as a
    do-nothing callback (EventsExecutor, rclpy 7.1)."""
    while keep_going():
        executor.spin_until_future_complete(Future(), timeout_sec=period)


def run_node(
    node_factory: Callable[[], Node], args: Sequence[str] | None = None, events: bool = False
) -> int:
    """Start rclpy, spin the node until Ctrl-C / SIGTERM / shutdown, then clean up.

    ``events``: spin rclpy's EventsExecutor (``rclpy.experimental``) instead of the
    SingleThreadedExecutor, whose every wait rebuilds a wait set of all the node's subscriptions,
    timers and services in Python: with a hundred vehicles' subscriptions that costs more than the
    messages. The EventsExecutor's ``spin()`` does not return when a signal shuts rclpy down
    (rclpy 7.1), so it spins half a second at a time and checks ``rclpy.ok()`` in between
    (:func:`spin_while`).

    SIGINT and SIGTERM reach rclpy as ``ExternalShutdownException``; ``destroy_node`` runs in
    ``finally`` so nodes that hold files (the recorder) close them completely, with a second
    SIGINT or SIGTERM ignored meanwhile (it raised KeyboardInterrupt inside ``destroy_node``).
    A node can end the process by calling ``rclpy.shutdown(context=...)`` (e.g. a player at the
    end of its bag).
    Before spinning, what the start-up made (the imported modules, the compiled kernels, the
    node and its engines) is collected once and frozen (``gc.freeze``): the collector's full
    passes then scan only what was made since. In the inference node at 100 vehicles a full
    pass over all of it took 50-100 ms, every callback waiting, about every half minute (one
    cause of the states' latency tail, EVALUATION.md section 4); it now takes about a
    millisecond. (What the start-up made and later drops in a cycle stays in memory, e.g. the
    first engines of a node whose rate changes: once, not per change.) Returns the exit
    status: 0, or 1 when the node could not be created. A command line rclpy cannot start with
    (a ``--params-file`` that is missing or malformed, a bad ``--ros-args`` argument) is reported
    in one ``ERROR:`` line, as a bad parameter is, instead of rcl's traceback.
    """
    limit_blas_threads()
    argv = list(args if args is not None else sys.argv)
    try:
        sections = check_params_files(argv)
        _init_quietly(argv)
    except StartupError as err:
        print(f'ERROR: {err}', file=sys.stderr)
        return 1
    except RuntimeError as err:  # RCLError: what rcl refuses that the checks above let through
        print(f'ERROR: cannot start: {_rcl_reason(err)}', file=sys.stderr)
        return 1
    node = None
    status = 0
    try:
        node = node_factory()
        for warning in params_files_for_others(sections, node.get_fully_qualified_name()):
            node.get_logger().warning(warning)
        executor = EventsExecutor() if events else SingleThreadedExecutor()
        executor.add_node(node)
        gc.collect()
        gc.freeze()  # (why: the docstring)
        if events:
            spin_while(executor, rclpy.ok, period=0.5)
        else:
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # rclpy's shutdown race (ros2/rclpy#398): a signal can shut the context down while the
        # executor builds its wait set, which raises RCLError (a RuntimeError) instead of
        # ExternalShutdownException. After a shutdown that is the end of spinning, not a failure.
        if rclpy.ok():
            raise
    except ParameterError as err:
        print(f'ERROR: {err}', file=sys.stderr)
        status = 1
    finally:
        # (a second Ctrl-C or SIGTERM must not cut the closing short: the recorder's bag)
        with uninterrupted(signal.SIGINT, signal.SIGTERM):
            gc.unfreeze()
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    return status


def params_files(argv: Sequence[str]) -> list[str]:
    """The files given with ``--params-file`` inside ``--ros-args`` sections of ``argv``."""
    files, in_ros_args, i = [], False, 0
    while i < len(argv):
        arg = argv[i]
        if arg == '--ros-args':
            in_ros_args = True
        elif arg == '--':
            in_ros_args = False
        elif in_ros_args and arg == '--params-file':
            if i + 1 >= len(argv):
                raise StartupError('--params-file needs a file name')
            files.append(argv[i + 1])
            i += 1
        i += 1
    return files


def check_params_files(argv: Sequence[str]) -> dict[str, list[str]]:
    """Refuse, with :class:`StartupError` naming the file and the problem, a ``--params-file``
    that cannot be read, is not YAML, or is not a mapping of node names to ``ros__parameters``
    (rcl would raise ``RCLError`` with a parser location, or, for a file that is not a mapping,
    start without a word). Returns each file's node sections (``/cloe_inference``, ``/**``,
    ``/fleet/cloe_shard1``: :func:`params_files_for_others`)."""
    sections: dict[str, list[str]] = {}
    for name in params_files(argv):
        sections[name] = []
        path = Path(name)
        try:
            text = path.read_text(encoding='utf-8')
        except FileNotFoundError:
            raise StartupError(f'parameter file {name}: it does not exist') from None
        except IsADirectoryError:
            raise StartupError(f'parameter file {name}: it is a folder, not a file') from None
        except PermissionError:
            raise StartupError(f'parameter file {name}: permission denied') from None
        except UnicodeDecodeError as err:
            raise StartupError(f'parameter file {name}: not a text file ({err.reason})') from err
        except OSError as err:
            raise StartupError(f'parameter file {name}: {err.strerror or err}') from err
        try:
            content = load(text)  # (as rcl reads it: cloe_ros.io.param_sections)
        except yaml.YAMLError as err:
            where = getattr(err, 'problem_mark', None)
            at = f' at line {where.line + 1}, column {where.column + 1}' if where else ''
            problem = getattr(err, 'problem', None) or str(err).splitlines()[0]
            raise StartupError(f'parameter file {name}: not valid YAML{at}: {problem}') from err
        if content is None:
            continue  # an empty file sets nothing, for rcl as for us
        if not isinstance(content, dict):
            raise StartupError(
                f'parameter file {name}: expected a mapping of node names to ros__parameters '
                f'(as in config/*.yaml), found {type(content).__name__} {brief(content)}'
            )
        try:
            check_layout(content)
            sections[name] = [section for section, _ in node_sections(content)]
        except ParamFileError as err:
            raise StartupError(f'parameter file {name}: {err}') from err
    return sections


def params_files_for_others(sections: dict[str, list[str]], node: str) -> list[str]:
    """A warning for each parameter file of ``sections`` (each file's node sections, as
    :func:`check_params_files` returns them) none of which applies to the node of fully
    qualified name ``node`` (rclpy's matching: :mod:`cloe_ros.io.param_sections`). ROS ignores
    such a file without a word, and the node runs on its defaults (e.g.
    ``config/inference.yaml``, whose section is ``cloe_inference``, given to a node renamed
    ``-r __node:=cloe_shard1``, or a section ``/other/cloe_shard1`` given to
    ``/fleet/cloe_shard1``)."""
    warnings = []
    for name, names in sections.items():
        if names and not any(applies(section, node) for section in names):
            warnings.append(
                f'parameter file {name}: it has parameters for {", ".join(names)}, not for '
                f'this node ({node}) nor /**: none of them apply (name its section {node}, or '
                'start the node under the name the file gives)'
            )
    return warnings


def _init_quietly(argv: list[str]) -> None:
    """``rclpy.init``; when it fails, rcl's own log line about it (``[ERROR] [rcl]: Failed to
    parse global arguments``) is held back, so the caller's ``ERROR:`` line is the only one."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            rclpy.init(args=argv)
        except BaseException:
            failed = True
            raise
        else:
            failed = False
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            text = held.read().decode(errors='replace')
            if failed:
                text = ''.join(
                    line
                    for line in text.splitlines(keepends=True)
                    if 'Failed to parse global arguments' not in line
                )
            sys.stderr.write(text)
            sys.stderr.flush()


def _rcl_reason(err: Exception) -> str:
    """rcl's message without its source locations (``, at /project/src/parse.c:782``)."""
    text = str(err).replace('failed to initialize rcl: ', '')
    return re.sub(r',? at [^,]*\.c:\d+', '', text).strip()


def describe(
    description: str,
    *,
    read_only: bool = False,
    float_range: tuple[float, float] | None = None,
    int_range: tuple[int, int] | None = None,
    additional_constraints: str = '',
    dynamic_typing: bool = False,
    parameter_type: int = ParameterType.PARAMETER_NOT_SET,
) -> ParameterDescriptor:
    """A ``ParameterDescriptor`` with an optional numeric range (step 0 = continuous)."""
    d = ParameterDescriptor(
        type=parameter_type,
        description=description,
        read_only=read_only,
        additional_constraints=additional_constraints,
        dynamic_typing=dynamic_typing,
    )
    if float_range is not None:
        d.floating_point_range = [
            FloatingPointRange(from_value=float(float_range[0]), to_value=float(float_range[1]))
        ]
    if int_range is not None:
        d.integer_range = [IntegerRange(from_value=int(int_range[0]), to_value=int(int_range[1]))]
    return d


def declare(node: Node, name: str, default, descriptor: ParameterDescriptor):
    """Declare a parameter and return its value.

    Friendlier than plain rclpy in two ways users hit on the command line: integers given for a
    floating-point parameter (``-p rate:=100``, ``-p gains:=[1, 2]``) are taken as floats, at
    start-up and in later ``set_parameters`` calls (see :func:`_integers_as_doubles`); and an
    array parameter with an empty default (``descriptor.type`` gives its element type) accepts
    ``[]`` and is always initialised (see :func:`_declare_array`). Any other invalid override
    (type or range) raises :class:`ParameterError` with rclpy's reason.
    """
    if not getattr(node, '_cloe_integers_as_doubles', False):
        node.add_pre_set_parameters_callback(lambda params: _integers_as_doubles(node, params))
        node._cloe_integers_as_doubles = True
    overrides = getattr(node, '_parameter_overrides', None)
    if not isinstance(overrides, dict):
        overrides = {}
    override = overrides.get(name)
    if override is not None and (
        isinstance(default, float) or (isinstance(default, list) and default)
    ):
        overrides[name] = _as_double(override, Parameter.Type.from_parameter_value(default).value)
    try:
        if isinstance(default, list) and not default:
            return _declare_array(node, name, descriptor)
        return node.declare_parameter(name, default, descriptor).value
    except (
        rclpy.exceptions.InvalidParameterTypeException,
        rclpy.exceptions.InvalidParameterValueException,
    ) as err:
        # (rclpy's text ends with the parameter's name, which the error names first)
        raise ParameterError(str(err).removesuffix(f': {name}'), name) from err


def _as_double(param: Parameter, wanted: int) -> Parameter:
    """``param`` with integers made floats when ``wanted`` (a ``ParameterType``) is a double or
    double array."""
    if wanted == ParameterType.PARAMETER_DOUBLE and param.type_ == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    if (
        wanted == ParameterType.PARAMETER_DOUBLE_ARRAY
        and param.type_ == Parameter.Type.INTEGER_ARRAY
    ):
        return Parameter(param.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in param.value])
    return param


def _integers_as_doubles(node: Node, params: list[Parameter]) -> list[Parameter]:
    """A pre-set-parameters callback: integers for a double (array) parameter become floats, as
    at start-up (rclpy would refuse them: "Wrong parameter type, expected DOUBLE got INTEGER").
    The parameter's type, as ``describe_parameters`` reports it, stays what it is."""
    out = []
    for p in params:
        if node.has_parameter(p.name):
            descriptor = node.describe_parameter(p.name)
            if not descriptor.dynamic_typing:
                p = _as_double(p, descriptor.type)
        out.append(p)
    return out


def _declare_array(node: Node, name: str, descriptor: ParameterDescriptor) -> list:
    """An array parameter whose default is empty. rclpy cannot hold an empty array of a given type
    (an empty list is a byte array to it), so it is declared with dynamic typing and the element
    type (``descriptor.type``) is checked here."""
    element = {
        ParameterType.PARAMETER_STRING_ARRAY: str,
        ParameterType.PARAMETER_DOUBLE_ARRAY: float,
        ParameterType.PARAMETER_INTEGER_ARRAY: int,
    }[descriptor.type]
    declared = ParameterDescriptor()
    declared.description = descriptor.description
    declared.additional_constraints = descriptor.additional_constraints
    declared.read_only = descriptor.read_only
    declared.dynamic_typing = True
    value = node.declare_parameter(name, [], declared).value
    if value is None or _is_empty_sequence(value):
        return []
    if isinstance(value, str) or not all(isinstance(v, element) for v in value):
        raise ParameterError(f'expected a list of {element.__name__}, got {value!r}', name)
    return list(value)


def _is_empty_sequence(value) -> bool:
    try:
        return not isinstance(value, str) and len(value) == 0
    except TypeError:
        return False


def refuse(reason: str) -> SetParametersResult:
    return SetParametersResult(successful=False, reason=reason)


def accept() -> SetParametersResult:
    return SetParametersResult(successful=True)


STRING_ARRAY = ParameterType.PARAMETER_STRING_ARRAY


def qos(reliable: bool = True, depth: int = 100, transient_local: bool = False) -> QoSProfile:
    """A keep-last QoS profile."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(
            DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE
        ),
    )


def vehicle_topic(vehicle: str, name: str) -> str:
    """``<vehicle>/<name>``, or ``name`` (relative to the node's namespace) for no vehicle."""
    vehicle = vehicle.rstrip('/')
    return f'{vehicle}/{name}' if vehicle else name


def incompatible_policy(kind) -> str:
    """The name of the QoS policy of an incompatible-QoS event (``reliability``, ``durability``,
    ...), from rclpy's ``last_policy_kind`` (``rmw_qos_policy_kind_t.RMW_QOS_POLICY_...``)."""
    name = getattr(kind, 'name', None) or str(kind)
    return name.rsplit('.', 1)[-1].removeprefix('RMW_QOS_POLICY_').lower()


def resolved_namespace(node, vehicle: str) -> str:
    """The absolute namespace of ``vehicle`` (an entry of ``vehicles``) in ``node``'s namespace,
    '/' for the root: where its topics are."""
    odom = node.resolve_topic_name(vehicle_topic(vehicle, 'odom'), only_expand=True)
    return odom[: -len('/odom')] or '/'


def check_same_namespaces(node, vehicles: Iterable[str]) -> None:
    """Refuse two ``vehicles`` (checked by :func:`check_vehicles`) that name one namespace
    once resolved against ``node``'s (``/uav1`` and ``uav1`` in the root namespace): the vehicle
    would be simulated, or inferred and published, twice."""
    seen: dict[str, str] = {}
    for v in vehicles:
        ns = resolved_namespace(node, v)
        if ns in seen:
            raise ParameterError(
                f'vehicles {seen[ns]!r} and {v!r} are the same namespace, {ns}: list it once',
                'vehicles')  # fmt: skip
        seen[ns] = v


def check_vehicles(vehicles: Iterable[str]) -> list[str]:
    """Validate a ``vehicles`` parameter: unique namespaces made of ``[A-Za-z0-9_/]``."""
    out = []
    for v in vehicles:
        v = v.strip()
        # (ASCII only: str.isalnum also takes letters that ROS names do not)
        if not v or any(not ((c.isascii() and c.isalnum()) or c in '_/') for c in v) or '//' in v:
            raise ParameterError(
                f'vehicle namespace {v!r} is not valid: use names like /uav1 (letters, digits, '
                '_ and /)',
                'vehicles',
            )
        digit = next((t for t in v.split('/') if t[:1].isdigit()), None)
        if digit is not None:  # (ROS refuses a name token that starts with a digit)
            raise ParameterError(
                f'vehicle namespace {v!r} must not start with a digit'
                + ('' if v.lstrip('/').startswith(digit) else f' (nor any part of it: {digit!r})'),
                'vehicles',
            )
        out.append(v.rstrip('/'))
    if len(set(out)) != len(out):
        raise ParameterError(f'vehicle namespaces must be unique, got {out}', 'vehicles')
    return out
