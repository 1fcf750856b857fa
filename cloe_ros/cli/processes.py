"""Running the package's nodes as separate processes on a private DDS domain (no rclpy here)."""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NODE_MODULES = {
    'quadrotor_sim': 'cloe_ros.ros.sim_node',
    'cloe_inference': 'cloe_ros.ros.inference_node',
    'bag_recorder': 'cloe_ros.ros.recorder_node',
    'bag_player': 'cloe_ros.ros.player_node',
}
_LOCKS: list = []


def reserve_domain_id(low: int = 100, high: int = 230) -> int:
    """A ``ROS_DOMAIN_ID`` in [low, high) that no other process of this package on the machine
    holds (a lock file per id, released when this process exits)."""
    lock_dir = Path(tempfile.gettempdir()) / 'cloe_ros_domains'
    lock_dir.mkdir(parents=True, exist_ok=True)
    start = low + (os.getpid() * 7) % (high - low)
    for k in range(high - low):
        domain = low + (start - low + k) % (high - low)
        fh = open(lock_dir / f'{domain}.lock', 'w')
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _LOCKS.append(fh)
        return domain
    raise RuntimeError(f'no free ROS domain id in [{low}, {high})')


def ros_env(domain_id: int, log_dir: Path) -> dict[str, str]:
    """Environment for node processes: the domain, DDS on localhost only, rcl logs in log_dir."""
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
        ROS_LOG_DIR=str(log_dir),
        PYTHONUNBUFFERED='1',
    )
    return env


def param_args(params: dict[str, object]) -> list[str]:
    """``-p name:=value`` arguments (booleans lower-case, lists as YAML flow sequences)."""
    out = []
    for key, value in params.items():
        if isinstance(value, bool):
            text = 'true' if value else 'false'
        elif isinstance(value, (list, tuple)):
            text = '[' + ', '.join(f"'{v}'" if isinstance(v, str) else str(v) for v in value) + ']'
        else:
            text = str(value)
        out += ['-p', f'{key}:={text}']
    return out


class NodeProcess:
    """One node in its own process (``python -m <module>``), output captured to a log file."""

    def __init__(
        self,
        executable: str,
        params: dict[str, object],
        env: dict[str, str],
        log_path: Path,
        node_name: str | None = None,
    ) -> None:
        self.name = node_name or executable
        self.log_path = log_path
        self._log = open(log_path, 'w')
        args = [sys.executable, '-m', NODE_MODULES[executable], '--ros-args']
        if node_name:
            args += ['-r', f'__node:={node_name}']
        args += param_args(params)
        self.proc = subprocess.Popen(
            args, env=env, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True
        )

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors='replace')

    def wait_for(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        return text in self.output()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Signal the node and wait for it; SIGKILL after ``timeout`` s. Returns the status."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._log.close()
        return self.proc.returncode
