r"""Which sections of a ROS 2 parameter file a node takes, as rclpy gives them to it.

A parameter file maps node names to ``ros__parameters``::

    /**:                      # every node
      ros__parameters: {rate: 50.0}
    fleet:                    # nested: the node /fleet/cloe_shard1
      cloe_shard1:
        ros__parameters: {shard_index: 1}
    /**/cloe_shard2:          # a node named cloe_shard2, in any namespace
      ros__parameters: {shard_index: 2}

A section's name is its keys joined by ``/`` with a leading ``/`` (``cloe_inference`` and
``/cloe_inference`` are the same section). It is a pattern of a node's fully qualified name in
which ``/*`` stands for one name and ``/**`` for any number of them, none included: rclcpp's
rule (``parameter_map_from``, ``/*`` becoming ``(/\w+)``), which rclpy follows. A node takes
every section that matches it, in the file's order, the later one's values winning: a ``/**``
written after a node's own section overrides it. (Measured with rclpy 7.1, Jazzy.)

The inference node warns at start-up of a file none of whose sections it takes
(:func:`cloe_ros.ros.common.params_files_for_others`), and ``cloe infer --config FILE --node
NAME`` reads a file as the node ``NAME`` takes it (:func:`cloe_ros.io.config.load_settings`).
No rclpy here.
"""

from __future__ import annotations

import re
from typing import Any

PARAMETERS = 'ros__parameters'


def node_sections(mapping: dict, where: str = '') -> list[tuple[str, dict[str, Any]]]:
    """The node sections of a parameter file's ``mapping``, in the file's order: ``(name,
    parameters)``, nested names joined (``/fleet/cloe_shard1``). Values that are not mappings
    are skipped (:func:`cloe_ros.ros.common.check_params_files` refuses them where the node
    reads the file)."""
    sections = []
    for key, value in mapping.items():
        if key == PARAMETERS or not isinstance(value, dict):
            continue
        name = f'{where}/{str(key).strip("/")}'
        parameters = value.get(PARAMETERS, False)
        if parameters is None or isinstance(parameters, dict):
            sections.append((name, parameters or {}))
        sections += node_sections(value, name)
    return sections


def fully_qualified(node: str) -> str:
    """A node name as a fully qualified one: ``cloe_shard1`` is ``/cloe_shard1``."""
    return '/' + node.strip('/')


def applies(section: str, node: str) -> bool:
    """Whether the section named ``section`` (as :func:`node_sections` names it) applies to the
    node of fully qualified name ``node``."""
    pattern = re.escape(section)
    pattern = pattern.replace(re.escape('/**'), r'(?:/\w+)*').replace(re.escape('/*'), r'(?:/\w+)')
    return re.fullmatch(pattern, node, re.ASCII) is not None


def parameters_for(mapping: dict, node: str) -> tuple[dict[str, Any], list[str]]:
    """The parameters the node ``node`` (fully qualified) takes from a parameter file's
    ``mapping``, and the names of all its sections (those that apply and those that do not)."""
    values: dict[str, Any] = {}
    sections = node_sections(mapping)
    for name, parameters in sections:
        if applies(name, node):
            values.update(parameters)
    return values, [name for name, _ in sections]
