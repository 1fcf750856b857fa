"""The README documents every node parameter with its real default (docs that match the code)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest
from rclpy.parameter import Parameter

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / 'scripts'))

from node_parameters import SHOWN_DEFAULTS, node_parameters  # noqa: E402

pytestmark = pytest.mark.ros


def _section(text: str, node: str) -> str:
    start = text.index(f'### `{node}`')
    end = text.find('\n### ', start + 1)
    return text[start:end]


def _rows(section: str) -> dict[str, str]:
    """parameter name -> the table row(s) naming it."""
    rows = {}
    for line in section.splitlines():
        if not line.startswith('| `'):
            continue
        first_cell = line.split('|')[1]
        for name in re.findall(r'`([^`]+)`', first_cell):
            rows[name] = line
    return rows


@pytest.mark.parametrize('node', ['quadrotor_sim', 'cloe_inference', 'bag_recorder', 'bag_player'])
def test_every_parameter_is_documented_with_its_default(node, tmp_path):
    from cloe_ros.ros.inference_node import InferenceNode
    from cloe_ros.ros.player_node import PlayerNode
    from cloe_ros.ros.recorder_node import BagRecorder
    from cloe_ros.ros.sim_node import SimulatorNode

    classes = {
        'quadrotor_sim': (SimulatorNode, ()),
        'cloe_inference': (InferenceNode, ()),
        'bag_recorder': (BagRecorder, (Parameter('output', value=str(tmp_path / 'bag')),)),
        'bag_player': (PlayerNode, (Parameter('bag', value=str(REPO / 'bags' / 'position')),)),
    }
    cls, overrides = classes[node]
    rows = _rows(_section((REPO / 'README.md').read_text(), node))
    params = node_parameters(cls, overrides)
    assert params
    for name, default, _ in params:
        assert name in rows, f'{node}: parameter {name} is not in the README'
        shown = SHOWN_DEFAULTS.get((node, name), default)
        cells = rows[name].split('|')
        # the default is in the second cell (combined rows list several, comma-separated)
        assert shown in cells[2], f'{node}: {name} default {shown} not in: {rows[name]}'
    undocumented = set(rows) - {name for name, _, _ in params}
    assert not undocumented, f'{node}: README documents parameters the node lacks: {undocumented}'
