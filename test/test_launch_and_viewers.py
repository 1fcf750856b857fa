"""The launch files, RViz configurations and Foxglove layouts name only what the package has.

``ros2 launch``, RViz and Foxglove cannot run here, so this checks what can be checked:

* the launch files use only the YAML frontend's ``arg`` and ``node`` (``pkg``, ``exec``, ``name``,
  ``namespace``, ``output``, ``param``, ``if``/``unless``) and ``$(var ...)`` of declared
  arguments;
* every executable is a console script of the package (setup.py);
* every parameter, evaluated as launch_ros evaluates it (substitutions, then YAML), exists on the
  node with that value: each node is built in-process with the launch file's parameters, so the
  node's own declarations and checks judge them (for every value of the arguments in ``if``);
* every topic the recorder is told to record is published by a node of the same launch file;
* every topic an RViz configuration or Foxglove layout shows is published or subscribed by the
  nodes of its launch file, and every frame is one the simulator stamps;
* the viewer files are what scripts/make_viewer_configs.py writes, and all of them install
  (setup.py data_files; a regular ``pip install .`` puts them under <prefix>/share/cloe_ros).

Pending, until the nodes have them (named here so that they show in the test's output):
:data:`PENDING_PARAMETERS`.
"""

from __future__ import annotations

import ast
import itertools
import json
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
LAUNCH = REPO / 'launch'
#: Launch file -> the viewer files of the same session (scripts/make_viewer_configs.py).
SESSIONS = {
    'demo.launch.yaml': ('viewers/rviz/cloe_demo.rviz', 'viewers/foxglove/cloe_demo.json'),
    'lab.launch.yaml': ('viewers/rviz/cloe_lab.rviz', 'viewers/foxglove/cloe_lab.json'),
}
#: Parameters a launch file sets that a node does not declare yet (none: cloe_inference's
#: ``discover`` is declared now).
PENDING_PARAMETERS: set[tuple[str, str]] = set()

NODE_KEYS = {'pkg', 'exec', 'name', 'namespace', 'output', 'param', 'if', 'unless'}
SUBSTITUTION = re.compile(r'\$\((\w[\w-]*)\s*([^)]*)\)')

pytestmark = pytest.mark.ros


# -- the launch files, evaluated as ros2 launch would --------------------------------------------


@dataclass
class LaunchNode:
    executable: str
    name: str
    namespace: str
    parameters: dict = field(default_factory=dict)


def console_scripts() -> dict[str, str]:
    """``name -> module:function`` of setup.py's console scripts."""
    tree = ast.parse((REPO / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                    entries = ast.literal_eval(value)
                    return dict(e.replace(' ', '').split('=', 1) for e in entries)
    raise AssertionError('setup.py has no console_scripts')


def substitute(text: str, args: dict[str, str]) -> str:
    def one(match: re.Match) -> str:
        kind, name = match.group(1), match.group(2).strip()
        assert kind == 'var', f'substitution $({kind} ...) is not checked here: {text!r}'
        assert name in args, f'$(var {name}) names no declared argument'
        return args[name]

    return SUBSTITUTION.sub(one, text)


def launch_value(value, args: dict[str, str]):
    """A parameter value as launch_ros hands it to the node: a string is substituted and read
    as YAML; a sequence must be non-empty and of one type (bool, int, float or str)."""
    if isinstance(value, str):
        value = yaml.safe_load(substitute(value, args))
    elif isinstance(value, list):
        value = [
            yaml.safe_load(substitute(v, args)) if isinstance(v, str) and '$(' in v else v
            for v in value
        ]
    if isinstance(value, list):
        assert value, 'launch_ros refuses an empty sequence'
        assert len({type(v) for v in value}) == 1, f'mixed types in {value}'
        assert type(value[0]) in (bool, int, float, str), value
        return value
    assert type(value) in (bool, int, float, str), f'launch_ros refuses {value!r}'
    return value


def truthy(text: str) -> bool:
    word = text.strip().lower()
    assert word in ('true', 'false', '1', '0'), f'not a launch condition: {text!r}'
    return word in ('true', '1')


def read_launch(path: Path) -> tuple[dict[str, str], list[dict]]:
    """Declared arguments (name -> default) and node entries of a YAML launch file."""
    doc = yaml.safe_load(path.read_text())
    assert list(doc) == ['launch'], f'{path.name}: expected a single "launch" key'
    args, nodes = {}, []
    for entry in doc['launch']:
        ((tag, body),) = entry.items()
        if tag == 'arg':
            assert set(body) <= {'name', 'default', 'description'}, body
            assert isinstance(body.get('default'), str), f'{body["name"]}: default as a string'
            args[body['name']] = body['default']
        elif tag == 'node':
            unknown = set(body) - NODE_KEYS
            assert not unknown, f'{path.name}: node keys not checked here: {unknown}'
            nodes.append(body)
        else:
            raise AssertionError(f'{path.name}: tag {tag!r} is not checked here')
    return args, nodes


def condition_args(args: dict[str, str], nodes: list[dict]) -> list[dict[str, str]]:
    """The defaults, and every combination of true/false for the arguments that ``if`` or
    ``unless`` use."""
    used = sorted({
        m.group(2).strip()
        for node in nodes for key in ('if', 'unless') if key in node
        for m in SUBSTITUTION.finditer(str(node[key]))
    })  # fmt: skip
    out = [dict(args)]
    for values in itertools.product(('true', 'false'), repeat=len(used)) if used else ():
        combination = {**args, **dict(zip(used, values))}
        if combination not in out:
            out.append(combination)
    return out


def evaluate(path: Path, args: dict[str, str]) -> list[LaunchNode]:
    _, nodes = read_launch(path)
    scripts = console_scripts()
    out = []
    for body in nodes:
        if 'if' in body and not truthy(substitute(str(body['if']), args)):
            continue
        if 'unless' in body and truthy(substitute(str(body['unless']), args)):
            continue
        assert body['pkg'] == 'cloe_ros', body
        executable = body['exec']
        assert executable in scripts, f'{executable} is not a console script of cloe_ros'
        params = {}
        for p in body.get('param', []):
            assert set(p) == {'name', 'value'}, p
            params[p['name']] = launch_value(p['value'], args)
        out.append(LaunchNode(executable, body.get('name', executable),
                              body.get('namespace', ''), params))  # fmt: skip
    return out


def launch_files() -> list[Path]:
    return sorted(LAUNCH.glob('*.launch.yaml'))


def test_every_launch_file_is_checked():
    assert [p.name for p in launch_files()] == sorted(SESSIONS)


# -- the nodes, built with the launch file's parameters ------------------------------------------


@dataclass
class Built:
    """What the nodes of one evaluation of a launch file declare, publish and subscribe."""

    parameters: dict[str, dict]  # node name -> declared parameter values
    published: set[str]
    subscribed: set[str]
    recorded: set[str]  # what recorders are told to record
    frames: set[str]
    pending: set[tuple[str, str]]


def node_classes() -> dict[str, type]:
    from cloe_ros.ros.inference_node import InferenceNode
    from cloe_ros.ros.player_node import PlayerNode
    from cloe_ros.ros.recorder_node import BagRecorder
    from cloe_ros.ros.sim_node import SimulatorNode

    classes = {'quadrotor_sim': SimulatorNode, 'cloe_inference': InferenceNode,
               'bag_recorder': BagRecorder, 'bag_player': PlayerNode}  # fmt: skip
    assert set(classes) == set(console_scripts()) - {'cloe'}, 'a node without a class here'
    return classes


def declared_value(node, name: str):
    """A declared parameter's value (None for a typed one without a value, e.g. an unset
    string array)."""
    import rclpy

    try:
        return node.get_parameter(name).value
    except rclpy.exceptions.ParameterUninitializedException:
        return None


def build(nodes: list[LaunchNode], tmp_path: Path) -> Built:
    import rclpy
    from rclpy.parameter import Parameter

    classes = node_classes()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    made = []
    built = Built({}, set(), set(), set(), set(), set())
    try:
        for k, spec in enumerate(nodes):
            params = dict(spec.parameters)
            if spec.executable == 'bag_recorder':
                params.setdefault('output', str(tmp_path / f'bag{k}'))  # not in the cwd
            overrides = [Parameter(n, value=v) for n, v in params.items()]
            cli = ['--ros-args', '-r', f'__node:={spec.name}']
            if spec.namespace:
                cli += ['-r', f'__ns:={spec.namespace}']
            node = classes[spec.executable](
                context=ctx, parameter_overrides=overrides, cli_args=cli
            )
            made.append(node)
            declared = {n: declared_value(node, n) for n in node._parameters}
            built.parameters[spec.name] = declared
            for name, value in spec.parameters.items():
                if name not in declared:
                    assert (spec.executable, name) in PENDING_PARAMETERS, (
                        f'{spec.name} ({spec.executable}) has no parameter {name!r}'
                    )
                    built.pending.add((spec.executable, name))
                    continue
                got = declared[name]
                if isinstance(got, float) or (isinstance(got, list) and got
                                              and isinstance(got[0], float)):  # fmt: skip
                    value = [float(v) for v in value] if isinstance(value, list) else float(value)
                assert list(got) == value if isinstance(value, list) else got == value, (
                    f'{spec.name}: {name} is {got!r}, the launch file gives {value!r}'
                )
            built.published |= {p.topic_name for p in node.publishers}
            built.subscribed |= {s.topic_name for s in node.subscriptions}
            if spec.executable == 'bag_recorder':
                built.recorded |= set(declared['topics'] or [])
            if spec.executable == 'quadrotor_sim':
                built.frames |= {node.world_frame, *node.body_frames.values()}
    finally:
        for node in made:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return built


@pytest.fixture(scope='module')
def evaluations(tmp_path_factory) -> dict[str, list[tuple[dict, Built]]]:
    """Per launch file: every evaluation (arguments) with what its nodes have."""
    out = {}
    for path in launch_files():
        args, nodes = read_launch(path)
        out[path.name] = [
            (a, build(evaluate(path, a), tmp_path_factory.mktemp(path.stem)))
            for a in condition_args(args, nodes)
        ]
    return out


@pytest.mark.parametrize('launch', sorted(SESSIONS))
def test_launch_file_names_only_what_the_package_has(launch, evaluations):
    for args, built in evaluations[launch]:
        assert built.parameters, f'{launch} with {args}: no node'
        # the recorder's topics are published by the nodes of the same launch
        unpublished = built.recorded - built.published
        assert not unpublished, f'{launch} with {args}: nobody publishes {unpublished}'
    if built.pending:
        print(f'{launch}: parameters not declared yet (pending): {sorted(built.pending)}')


def test_the_demo_launch_is_the_demo(evaluations):
    """As `cloe demo`: the simulator waits for every inference node and the recorder, the three
    algorithms publish under their own output namespace."""
    from cloe_ros.cli.demo import ALGORITHMS

    ((_, built),) = evaluations['demo.launch.yaml']
    inference = {n: p for n, p in built.parameters.items() if n.startswith('cloe_inference')}
    assert sorted(p['algorithm'] for p in inference.values()) == sorted(a for a, _ in ALGORITHMS)
    assert all(p['output_ns'] == p['algorithm'] for p in inference.values())
    sim = built.parameters['quadrotor_sim']
    assert sim['wait_for_subscribers'] == len(inference) + 1 and sim['shutdown_when_done']
    for alg, _ in ALGORITHMS:
        assert {f'/{alg}/state', f'/{alg}/parameters', f'/{alg}/prediction'} <= built.recorded


def test_the_lab_launch_takes_its_vehicles_from_one_argument(evaluations):
    for args, built in evaluations['lab.launch.yaml']:
        vehicles = yaml.safe_load(args['vehicles'])
        assert built.parameters['cloe_inference']['vehicles'] == vehicles
        # the argument reaches the node's parameter of the same name (a bool)
        assert built.parameters['cloe_inference']['discover'] is truthy(args['discover'])
        for v in vehicles:
            assert {f'{v}/odom', f'{v}/reference'} <= built.subscribed
            assert f'{v}/cloe/state' in built.published
        if truthy(args['simulate']):
            assert built.parameters['quadrotor_sim']['vehicles'] == vehicles
            assert {f'{v}/odom' for v in vehicles} <= built.published
        else:
            assert 'quadrotor_sim' not in built.parameters


# -- the viewer configurations -------------------------------------------------------------------


def rviz_names(path: Path) -> tuple[set[str], set[str]]:
    """Topics and frames an RViz configuration names."""
    config = yaml.safe_load(path.read_text())
    manager = config['Visualization Manager']
    topics, frames = set(), {manager['Global Options']['Fixed Frame']}

    def walk(displays):
        for d in displays:
            assert d['Class'].startswith(('rviz_default_plugins/', 'rviz_common/')), d['Class']
            if 'Topic' in d:
                topics.add(d['Topic']['Value'])
            frame = d.get('Reference Frame', '<Fixed Frame>')
            if frame != '<Fixed Frame>':
                frames.add(frame)
            walk(d.get('Displays', []))

    walk(manager['Displays'])
    target = manager['Views']['Current'].get('Target Frame', '<Fixed Frame>')
    if target != '<Fixed Frame>':
        frames.add(target)
    return topics, frames


def foxglove_names(path: Path) -> tuple[set[str], set[str]]:
    """Topics and frames a Foxglove layout names (3D topics, plot and raw-message paths, the
    diagnostics topic; the 3D panel's frames)."""
    layout = json.loads(path.read_text())
    topics, frames = set(), set()
    panels = layout['configById']

    def used(tree) -> set[str]:
        if isinstance(tree, str):
            return {tree}
        return used(tree['first']) | used(tree['second'])

    assert used(layout['layout']) == set(panels), 'a panel is configured but not placed'
    for panel_id, config in panels.items():
        kind = panel_id.split('!')[0]
        if kind == '3D':
            topics |= set(config['topics'])
            frames.add(config['followTf'])
            frames |= {layer['frameId'] for layer in config['layers'].values()}
        elif kind == 'Plot':
            topics |= {p['value'].split('.')[0] for p in config['paths']}
        elif kind == 'RawMessages':
            topics.add(config['topicPath'].split('.')[0])
        elif kind == 'DiagnosticSummary':
            topics.add(config['topicToRender'])
        else:
            raise AssertionError(f'panel {panel_id} is not checked here')
    return topics, frames


@pytest.mark.parametrize('launch', sorted(SESSIONS))
def test_viewers_show_only_what_the_nodes_have(launch, evaluations):
    built = [b for _, b in evaluations[launch]]
    have = set().union(*(b.published | b.subscribed for b in built))
    frames = set().union(*(b.frames for b in built))
    for relative in SESSIONS[launch]:
        path = REPO / relative
        topics, named = (rviz_names if path.suffix == '.rviz' else foxglove_names)(path)
        missing = topics - have
        assert not missing, f'{relative} shows topics no node of {launch} has: {missing}'
        assert named <= frames, f'{relative}: frames {named - frames} (the package: {frames})'


def test_viewer_files_are_what_the_script_writes():
    check = subprocess.run(
        [sys.executable, str(REPO / 'scripts' / 'make_viewer_configs.py'), '--check'],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert check.returncode == 0, check.stdout + check.stderr


# -- installation --------------------------------------------------------------------------------


def shipped() -> list[str]:
    files = [f'launch/{p.name}' for p in launch_files()]
    return files + [f for pair in SESSIONS.values() for f in pair]


def installed_as(relative: str) -> str:
    """Where a shipped file goes under share/cloe_ros (viewers/rviz/x.rviz -> rviz/x.rviz)."""
    return relative.removeprefix('viewers/')


def test_setup_installs_every_file():
    """setup.py's data_files put each file under share/cloe_ros/<folder>/ (colcon and pip)."""
    setup = (REPO / 'setup.py').read_text()
    for relative in shipped():
        folder = Path(installed_as(relative)).parent.name
        pattern = {'launch': 'launch/*.launch.yaml', 'rviz': 'viewers/rviz/*.rviz',
                   'foxglove': 'viewers/foxglove/*.json'}[folder]  # fmt: skip
        assert f"(f'share/{{PACKAGE}}/{folder}', glob('{pattern}'))" in setup, relative
        assert Path(relative).match(pattern)


def test_installed_under_the_prefix():
    """The regular install of `make install` (`pip install .`) holds the same files under
    <prefix>/share/cloe_ros."""
    share = Path(sys.prefix) / 'share' / 'cloe_ros'
    if not (share / 'package.xml').is_file():
        pytest.skip(f'cloe_ros is not installed into {sys.prefix} (run `make install`)')
    for relative in shipped():
        installed = share / installed_as(relative)
        assert installed.is_file(), f'{installed} is missing: run `make install`'
        assert installed.read_text() == (REPO / relative).read_text(), f'{installed} is stale'
