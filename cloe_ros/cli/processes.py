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
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Sequence

NODE_MODULES = {
    'quadrotor_sim': 'cloe_ros.ros.sim_node',
    'cloe_inference': 'cloe_ros.ros.inference_node',
    'bag_recorder': 'cloe_ros.ros.recorder_node',
    'bag_player': 'cloe_ros.ros.player_node',
}
#: The lock file held for each domain this process reserved.
_LOCKS: dict[int, object] = {}


def reserve_domain_id(low: int = 100, high: int = 230) -> int:
    """A ``ROS_DOMAIN_ID`` in [low, high) that no other process of this package on the machine
    holds (a lock file per id, held until :func:`release_domain_id` or until this process
    exits)."""
    lock_dir = Path(tempfile.gettempdir()) / 'cloe_ros_domains'
    lock_dir.mkdir(parents=True, exist_ok=True)
    start = low + (os.getpid() * 7) % (high - low)
    for k in range(high - low):
        domain = low + (start - low + k) % (high - low)
        if domain in _LOCKS:
            continue
        fh = open(lock_dir / f'{domain}.lock', 'w')
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _LOCKS[domain] = fh
        return domain
    raise RuntimeError(f'no free ROS domain id in [{low}, {high})')


def release_domain_id(domain: int) -> None:
    """Give back a domain :func:`reserve_domain_id` reserved (nothing if it holds none): once
    every node on it has ended, another process may use it."""
    fh = _LOCKS.pop(domain, None)
    if fh is not None:
        fh.close()  # (closing the file releases its lock)


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
    """One node in its own process (and process group), its output captured to files.

    By default the node runs as ``python -m <module>`` (:data:`NODE_MODULES`); ``command``
    runs another program in its place, e.g. the installed console script. Standard output goes
    to ``log_path``, and so does standard error unless ``stderr_path`` is given. ``node_name``
    renames the node (``-r __node:=<name>``); ``extra_args`` come after the parameters."""

    def __init__(
        self,
        executable: str,
        params: dict[str, object],
        env: dict[str, str],
        log_path: Path,
        node_name: str | None = None,
        *,
        extra_args: Sequence[str] = (),
        command: Sequence[str] | None = None,
        stderr_path: Path | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.name = node_name or executable
        self.log_path = log_path
        self.stderr_path = stderr_path
        self._log = open(log_path, 'w')
        self._err = open(stderr_path, 'w') if stderr_path is not None else None
        args = [*(command or [sys.executable, '-m', NODE_MODULES[executable]]), '--ros-args']
        if node_name:
            args += ['-r', f'__node:={node_name}']
        args += [*param_args(params), *extra_args]
        self.proc = subprocess.Popen(
            args,
            env=env,
            stdout=self._log,
            stderr=self._err if self._err is not None else subprocess.STDOUT,
            cwd=cwd,
            start_new_session=True,
        )

    def output(self) -> str:
        """Everything the process wrote so far (standard output, then standard error if it has
        a file of its own); also after :meth:`stop`."""
        text = ''
        for fh, path in ((self._log, self.log_path), (self._err, self.stderr_path)):
            if fh is not None and path is not None:
                if not fh.closed:
                    fh.flush()
                text += path.read_text(errors='replace')
        return text

    def errors(self) -> str:
        """What the process wrote to standard error (all its output if that was not separate)."""
        if self.stderr_path is None:
            return self.output()
        return self.stderr_path.read_text(errors='replace')

    def wait_for(self, text: str, timeout: float) -> bool:
        """Whether ``text`` appears in the output within ``timeout`` s (False at once if the
        process ends without it)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        return text in self.output()

    def wait(self, timeout: float) -> int:
        """The exit status, once the process has ended (``subprocess.TimeoutExpired`` after
        ``timeout`` s)."""
        return self.proc.wait(timeout)

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Signal the node and wait for it; SIGKILL after ``timeout`` s. Returns the status
        (nothing is sent to a process that has ended)."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._log.close()
        if self._err is not None:
            self._err.close()
        return self.proc.returncode
