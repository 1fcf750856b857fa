"""Print the parameters of every node as Markdown tables (name, default, description/range).

Used to write the README's node reference; `test/test_readme.py` checks the README against the
nodes' actual declarations.
"""

from __future__ import annotations

import sys
import tempfile

import rclpy
from rclpy.parameter import Parameter

#: Defaults that depend on the run (given here as the documentation states them).
SHOWN_DEFAULTS = {('bag_recorder', 'output'): 'cloe_bag_<YYYYmmdd_HHMMSS>',
                  ('bag_player', 'bag'): '(required)'}  # fmt: skip


def node_parameters(node_cls, overrides=()) -> list[tuple[str, str, str]]:
    """(name, default, description with range) of every parameter a node declares."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = node_cls(context=ctx, parameter_overrides=list(overrides))
        rows = []
        for name in sorted(node._parameters):
            if name in ('use_sim_time', 'start_type_description_service'):
                continue  # rclpy's own
            desc = node.describe_parameter(name)
            try:
                value = node.get_parameter(name).value
            except rclpy.exceptions.ParameterUninitializedException:
                value = None  # typed array without a default: empty
            if value is None or (isinstance(value, (list, tuple)) and not len(value)):
                text = '[]'
            elif isinstance(value, bool):
                text = str(value).lower()
            elif isinstance(value, (list, tuple)):
                text = '[' + ', '.join(f'{v:g}' if isinstance(v, float) else str(v)
                                       for v in value) + ']'  # fmt: skip
            elif isinstance(value, float):
                text = f'{value:g}'
            elif isinstance(value, str):
                text = f"'{value}'" if value == '' else value
            else:
                text = str(value)
            extra = []
            if desc.floating_point_range:
                r = desc.floating_point_range[0]
                extra.append(f'[{r.from_value:g}, {r.to_value:g}]')
            if desc.integer_range:
                r = desc.integer_range[0]
                extra.append(f'[{r.from_value}, {r.to_value}]')
            if desc.read_only:
                extra.append('read-only')
            rows.append((name, text, desc.description + (f' ({"; ".join(extra)})' if extra
                                                          else '')))  # fmt: skip
        node.destroy_node()
        return rows
    finally:
        rclpy.try_shutdown(context=ctx)


def main() -> int:
    from cloe_ros.ros.inference_node import InferenceNode
    from cloe_ros.ros.player_node import PlayerNode
    from cloe_ros.ros.recorder_node import BagRecorder
    from cloe_ros.ros.sim_node import SimulatorNode

    tmp = tempfile.mkdtemp()
    bag = sys.argv[1] if len(sys.argv) > 1 else 'bags/position'
    nodes = [
        ('quadrotor_sim', SimulatorNode, ()),
        ('cloe_inference', InferenceNode, ()),
        ('bag_recorder', BagRecorder, (Parameter('output', value=f'{tmp}/bag'),)),
        (
            'bag_player',
            PlayerNode,
            (Parameter('bag', value=bag),),
        ),
    ]
    for title, cls, overrides in nodes:
        print(f'#### `{title}` parameters\n')
        print('| parameter | default | meaning |')
        print('|---|---|---|')
        for name, default, desc in node_parameters(cls, overrides):
            default = SHOWN_DEFAULTS.get((title, name), default)
            print(f'| `{name}` | `{default}` | {desc} |')
        print()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
