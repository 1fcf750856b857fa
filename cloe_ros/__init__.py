"""cloe_ros: online trajectory inference of quadrotors with CLOE / CLOE-SM on ROS 2."""

__version__ = '0.1.0'
