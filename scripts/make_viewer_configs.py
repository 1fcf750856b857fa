"""Write the RViz configurations (viewers/rviz/*.rviz) and Foxglove layouts
(viewers/foxglove/*.json) of the
package's topics, one pair per session the launch files start:

* ``demo``: one un-namespaced vehicle, three inference outputs (``/cloe``, ``/cloe_sm``,
  ``/cloe_iv``), as ``cloe demo`` and ``launch/demo.launch.yaml`` run them;
* ``lab``: vehicles ``/uav1`` ... ``/uav3``, one output each (``<ns>/cloe``), as
  ``launch/lab.launch.yaml`` runs them.

Per vehicle they show ``odom`` (measured), ``reference``, ``<out>/state`` (inferred, with its
covariance), ``<out>/prediction`` (nav_msgs/Path) and ``<out>/prediction_markers`` (MarkerArray,
spheres of the 95 % prediction radius), in the ``world`` frame; the Foxglove layout adds plots of
the position (measured, inferred), ``/diagnostics`` and the raw ``<out>/parameters``.

    python scripts/make_viewer_configs.py          # rewrite the files
    python scripts/make_viewer_configs.py --check  # exit 1 if a file differs (test_viewer_configs)
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
WORLD = 'world'
#: One colour per output (RViz "R; G; B", Foxglove "#rrggbb").
COLOURS = ('#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#ff7f0e', '#8c564b')
MEASURED = '#7f7f7f'
REFERENCE = '#bcbd22'


@dataclass(frozen=True)
class Session:
    name: str
    title: str
    vehicles: tuple[str, ...]  # '' for the un-namespaced vehicle
    outputs: tuple[str, ...]  # output_ns of the inference nodes


SESSIONS = (
    Session('demo', 'cloe_ros demo: one vehicle, CLOE / CLOE-SM / CLOE-IV', ('',),
            ('cloe', 'cloe_sm', 'cloe_iv')),
    Session('lab', 'cloe_ros lab session: /uav1 ... /uav3', ('/uav1', '/uav2', '/uav3'),
            ('cloe',)),
)  # fmt: skip


def topic(vehicle: str, *parts: str) -> str:
    return '/'.join([vehicle.rstrip('/'), *parts]) if vehicle else '/' + '/'.join(parts)


def label(vehicle: str) -> str:
    return vehicle or '/'


def rgb(colour: str) -> str:
    return '; '.join(str(int(colour[i : i + 2], 16)) for i in (1, 3, 5))


# -- RViz --------------------------------------------------------------------------------------


def _topic(name: str, depth: int = 10) -> dict:
    return {
        'Value': name,
        'Depth': depth,
        'History Policy': 'Keep Last',
        'Reliability Policy': 'Reliable',
        'Durability Policy': 'Volatile',
    }


def _odometry(name: str, title: str, colour: str, covariance: bool) -> dict:
    return {
        'Class': 'rviz_default_plugins/Odometry',
        'Name': title,
        'Enabled': True,
        'Topic': _topic(name),
        'Keep': 200,
        'Position Tolerance': 0.05,
        'Angle Tolerance': 0.5,
        'Shape': {'Value': 'Axes', 'Axes Length': 0.2, 'Axes Radius': 0.02},
        'Covariance': {
            'Value': covariance,
            'Position': {'Value': True, 'Color': rgb(colour), 'Alpha': 0.3, 'Scale': 1},
            'Orientation': {'Value': False},
        },
    }


def rviz_config(session: Session) -> dict:
    groups = []
    for vehicle in session.vehicles:
        displays = [
            _odometry(topic(vehicle, 'odom'), 'odom (measured)', MEASURED, covariance=False),
            {
                'Class': 'rviz_default_plugins/Pose',
                'Name': 'reference',
                'Enabled': True,
                'Topic': _topic(topic(vehicle, 'reference')),
                'Shape': 'Axes',
                'Axes Length': 0.3,
                'Axes Radius': 0.03,
            },
        ]
        for k, out in enumerate(session.outputs):
            colour = COLOURS[k % len(COLOURS)]
            displays += [
                _odometry(topic(vehicle, out, 'state'), f'{out}/state (inferred, covariance)',
                          colour, covariance=True),
                {
                    'Class': 'rviz_default_plugins/Path',
                    'Name': f'{out}/prediction',
                    'Enabled': True,
                    'Topic': _topic(topic(vehicle, out, 'prediction')),
                    'Color': rgb(colour),
                    'Alpha': 1,
                    'Line Style': 'Lines',
                    'Buffer Length': 1,
                    'Pose Style': 'None',
                },
                {
                    'Class': 'rviz_default_plugins/MarkerArray',
                    'Name': f'{out}/prediction_markers (95 % radius)',
                    'Enabled': True,
                    'Topic': _topic(topic(vehicle, out, 'prediction_markers')),
                    'Namespaces': {},
                },
            ]  # fmt: skip
        groups.append({'Class': 'rviz_common/Group', 'Name': f'vehicle {label(vehicle)}',
                       'Enabled': True, 'Displays': displays})  # fmt: skip
    return {
        'Panels': [
            {'Class': 'rviz_common/Displays', 'Name': 'Displays'},
            {'Class': 'rviz_common/Views', 'Name': 'Views'},
        ],
        'Visualization Manager': {
            'Class': '',
            'Displays': [
                {
                    'Class': 'rviz_default_plugins/Grid',
                    'Name': 'Grid',
                    'Enabled': True,
                    'Reference Frame': '<Fixed Frame>',
                    'Plane': 'XY',
                    'Plane Cell Count': 20,
                    'Cell Size': 1,
                },
                *groups,
            ],
            'Enabled': True,
            'Global Options': {
                'Background Color': '48; 48; 48',
                'Fixed Frame': WORLD,
                'Frame Rate': 30,
            },
            'Name': 'root',
            'Tools': [
                {'Class': 'rviz_default_plugins/Interact', 'Hide Inactive Objects': True},
                {'Class': 'rviz_default_plugins/MoveCamera'},
                {'Class': 'rviz_default_plugins/Select'},
            ],
            'Value': True,
            'Views': {
                'Current': {
                    'Class': 'rviz_default_plugins/Orbit',
                    'Name': 'Current View',
                    'Target Frame': '<Fixed Frame>',
                    'Distance': 10,
                    'Focal Point': {'X': 0.5, 'Y': 1.0 * len(session.vehicles), 'Z': 0.5},
                    'Pitch': 0.6,
                    'Yaw': 3.9,
                    'Value': 'Orbit (rviz_default_plugins)',
                },
                'Saved': None,
            },
        },
        'Window Geometry': {'Height': 900, 'Width': 1400, 'Displays': {'collapsed': False}},
    }


# -- Foxglove ----------------------------------------------------------------------------------


def foxglove_layout(session: Session) -> dict:
    topics: dict[str, dict] = {}
    position_paths, height_paths = [], []
    for vehicle in session.vehicles:
        topics[topic(vehicle, 'odom')] = {'visible': True, 'type': 'axis', 'axisScale': 0.3}
        topics[topic(vehicle, 'reference')] = {'visible': True, 'type': 'arrow',
                                               'color': REFERENCE}  # fmt: skip
        for axis, paths in (('x', position_paths), ('z', height_paths)):
            paths.append({
                'value': f'{topic(vehicle, "odom")}.pose.pose.position.{axis}',
                'enabled': True, 'timestampMethod': 'headerStamp', 'color': MEASURED,
                'label': f'{label(vehicle)} {axis} measured',
            })  # fmt: skip
        for k, out in enumerate(session.outputs):
            colour = COLOURS[k % len(COLOURS)]
            topics[topic(vehicle, out, 'state')] = {
                'visible': True, 'type': 'arrow', 'color': colour, 'showCovariance': True,
                'covarianceColor': colour + '55',
            }  # fmt: skip
            topics[topic(vehicle, out, 'prediction')] = {
                'visible': True, 'type': 'line', 'lineWidth': 0.03,
                'gradient': [colour + 'ff', colour + '22'],
            }  # fmt: skip
            topics[topic(vehicle, out, 'prediction_markers')] = {'visible': True}
            for axis, paths in (('x', position_paths), ('z', height_paths)):
                paths.append({
                    'value': f'{topic(vehicle, out, "state")}.pose.pose.position.{axis}',
                    'enabled': True, 'timestampMethod': 'headerStamp', 'color': colour,
                    'label': f'{label(vehicle)} {axis} {out}',
                })  # fmt: skip
    first = session.vehicles[0]
    parameters = topic(first, session.outputs[-1], 'parameters')

    def plot(title: str, paths: list[dict]) -> dict:
        return {'title': title, 'paths': paths, 'showLegend': True, 'legendDisplay': 'floating',
                'showXAxisLabels': True, 'showYAxisLabels': True, 'isSynced': True,
                'xAxisVal': 'timestamp', 'followingViewWidth': 30}  # fmt: skip

    config_by_id = {
        '3D!cloe': {
            'cameraState': {'distance': 12, 'perspective': True, 'phi': 55, 'thetaOffset': 40,
                            'target': [0.5, 1.0 * len(session.vehicles), 0.5],
                            'targetOffset': [0, 0, 0], 'targetOrientation': [0, 0, 0, 1],
                            'fovy': 45, 'near': 0.5, 'far': 5000},
            'followMode': 'follow-none',
            'followTf': WORLD,
            'scene': {'transforms': {'visible': False}},
            'transforms': {},
            'topics': topics,
            'layers': {'grid': {'visible': True, 'layerId': 'foxglove.Grid', 'frameId': WORLD,
                                'size': 20, 'divisions': 20, 'lineWidth': 1,
                                'color': '#248eff66', 'position': [0, 0, 0],
                                'rotation': [0, 0, 0]}},
            'publish': {'type': 'point', 'poseTopic': '/move_base_simple/goal',
                        'pointTopic': '/clicked_point', 'poseEstimateTopic': '/initialpose'},
            'imageMode': {},
        },
        'Plot!x': plot('x: measured and inferred [m]', position_paths),
        'Plot!z': plot('z: measured and inferred [m]', height_paths),
        'DiagnosticSummary!cloe': {'topicToRender': '/diagnostics', 'minLevel': 0,
                                   'pinnedIds': [], 'hardwareIdFilter': '',
                                   'sortByLevel': True},
        'RawMessages!parameters': {'topicPath': parameters, 'diffEnabled': False,
                                   'diffMethod': 'custom', 'diffTopicPath': '',
                                   'showFullMessageForDiff': False, 'expansion': 'all'},
    }  # fmt: skip
    return {
        'configById': config_by_id,
        'globalVariables': {},
        'userNodes': {},
        'playbackConfig': {'speed': 1},
        'layout': {
            'direction': 'row',
            'first': '3D!cloe',
            'second': {
                'direction': 'column',
                'first': {'direction': 'column', 'first': 'Plot!x', 'second': 'Plot!z'},
                'second': {'direction': 'row', 'first': 'DiagnosticSummary!cloe',
                           'second': 'RawMessages!parameters'},
                'splitPercentage': 60,
            },
            'splitPercentage': 55,
        },
    }  # fmt: skip


def render(session: Session) -> dict[Path, str]:
    """File path -> text for one session."""
    header = (
        f'# RViz 2 configuration for the {session.name} session of cloe_ros ({session.title}).\n'
        '# Written by scripts/make_viewer_configs.py: change that, not this file.\n'
    )
    rviz = header + yaml.safe_dump(rviz_config(session), sort_keys=False, width=99)
    layout = json.dumps(foxglove_layout(session), indent=2) + '\n'
    return {
        REPO / 'viewers' / 'rviz' / f'cloe_{session.name}.rviz': rviz,
        REPO / 'viewers' / 'foxglove' / f'cloe_{session.name}.json': layout,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='compare instead of writing')
    args = parser.parse_args(argv)
    stale = []
    for session in SESSIONS:
        for path, text in render(session).items():
            if args.check:
                if not path.is_file() or path.read_text() != text:
                    stale.append(path)
                continue
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            print(f'wrote {path.relative_to(REPO)}')
    for path in stale:
        print(f'{path.relative_to(REPO)} differs from what {Path(__file__).name} writes')
    return 1 if stale else 0


if __name__ == '__main__':
    sys.exit(main())
