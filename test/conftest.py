"""Test-wide settings: DDS on this machine only, a domain id of our own, rcl logs out of ~/.ros."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from ros_helpers import reserve_domain_id

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ['ROS_DOMAIN_ID'] = str(reserve_domain_id())
os.environ.setdefault('ROS_LOG_DIR', os.path.join(tempfile.gettempdir(), 'cloe_ros_test_logs'))
os.environ.setdefault('MPLBACKEND', 'Agg')
