"""Test-wide settings: keep DDS on this machine and rcl logs out of ~/.ros."""

from __future__ import annotations

import os
import tempfile

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_LOG_DIR', os.path.join(tempfile.gettempdir(), 'cloe_ros_test_logs'))
os.environ.setdefault('MPLBACKEND', 'Agg')
