"""ament_python package cloe_ros (also pip-installable: `pip install .`)."""

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'cloe_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.yaml')),
        (f'share/{PACKAGE}/rviz', glob('viewers/rviz/*.rviz')),
        (f'share/{PACKAGE}/foxglove', glob('viewers/foxglove/*.json')),
        *[
            (f'share/{PACKAGE}/bags/{os.path.basename(os.path.normpath(d))}', glob(f'{d}*'))
            for d in sorted(glob('bags/*/'))
        ],
    ],
    install_requires=[
        'setuptools',
        'numpy>=1.24',
        'scipy>=1.10',
        'matplotlib>=3.6',
        'pyyaml>=6',
        'rosbags>=0.10',
        # MCAP records and CRCs: the writer of the package's bags, the reader's record decoding
        'mcap>=1.6',
        # one BLAS thread in the package's processes (cloe_ros/threads.py)
        'threadpoolctl>=3.5',
        # compiled kernels of the per-vehicle hot paths (cloe_ros/core/kernels.py)
        'numba>=0.60',
    ],
    extras_require={
        # `cloe live`: the Foxglove WebSocket server (a 19 MB wheel, 53 MB installed)
        'live': ['foxglove-sdk>=0.30'],
        'test': ['pytest>=7', 'mcap-ros2-support>=0.5', 'websockets>=12'],
    },
    python_requires='>=3.10',
    zip_safe=True,
    maintainer='cloe_ros maintainers',
    maintainer_email='maintainers@cloe-ros.invalid',
    description='Online trajectory inference of quadrotors with CLOE / CLOE-SM on ROS 2.',
    license='BSD-3-Clause',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'cloe = cloe_ros.cli.main:main',
            'quadrotor_sim = cloe_ros.ros.sim_node:main',
            'cloe_inference = cloe_ros.ros.inference_node:main',
            'bag_recorder = cloe_ros.ros.recorder_node:main',
            'bag_player = cloe_ros.ros.player_node:main',
        ],
    },
)
