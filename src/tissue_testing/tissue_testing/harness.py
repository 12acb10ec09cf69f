"""Real-process test harness: start installed node executables on an isolated DDS domain.

Tests start nodes exactly as ``ros2 run <pkg> <exe>`` would: the console script installed under
``install/<pkg>/lib/<pkg>/<exe>``. Every test session picks its own ``ROS_DOMAIN_ID`` and restricts
discovery to localhost, so parallel runs on one machine never see each other's topics.
"""

from __future__ import annotations

import ctypes
import os
import random
import re
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Mapping

import yaml

#: the workspace: this file is src/tissue_testing/tissue_testing/harness.py (installed as a symlink)
REPO_ROOT = Path(__file__).resolve().parents[3]
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the child before exec: default SIGINT; SIGKILL when the test process dies (even killed).

    Nodes run in their own session (so a Ctrl-C of pytest is not delivered twice); without this a
    killed test run would leave them running, e.g. a 1 kHz driver on a test domain.
    """
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    # a test run started as a background job ignores SIGINT, and exec would pass that on: nodes
    # must still stop on SIGINT like ros2 run does on Ctrl-C
    signal.signal(signal.SIGINT, signal.SIG_DFL)


INSTALL = REPO_ROOT / 'install'

# Domain ids 0..101 are the ones whose ports never collide with the ephemeral range on Linux.
_DOMAIN_LOCK = threading.Lock()
_DOMAIN_STATE = {'next': None}


def _domain_block() -> range:
    """The domain ids this process may use: all of 1..100, or its share when pytest-xdist runs the
    suite in several workers (so two workers never share a domain)."""
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    count = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1') or 1)
    if not worker.startswith('gw') or count <= 1:
        return range(1, 101)
    size = 100 // count
    index = int(worker[2:]) % count
    return range(1 + index * size, 1 + (index + 1) * size)


def new_domain_id() -> int:
    """A domain id unlikely to be used by another test run on this machine (1..100)."""
    with _DOMAIN_LOCK:
        block = _domain_block()
        if _DOMAIN_STATE['next'] is None:
            _DOMAIN_STATE['next'] = random.Random(os.getpid() ^ time.time_ns()).randrange(len(block))
        k = _DOMAIN_STATE['next']
        _DOMAIN_STATE['next'] = (k + 1) % len(block)
        return block[k]


def ros_env(domain_id: int | None = None, base: Mapping[str, str] | None = None) -> dict:
    """Environment for a node process: isolated domain, localhost discovery, unbuffered output."""
    env = dict(os.environ if base is None else base)
    env['ROS_DOMAIN_ID'] = str(new_domain_id() if domain_id is None else domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    env['PYTHONUNBUFFERED'] = '1'
    # Colour codes in ROS log lines get in the way of regex matching.
    env['RCUTILS_COLORIZED_OUTPUT'] = '0'
    return env


def executable(pkg: str, exe: str) -> Path:
    """Path of an installed node executable, where ``ros2 run`` looks it up."""
    path = INSTALL / pkg / 'lib' / pkg / exe
    assert path.is_file() and os.access(path, os.X_OK), (
        f'{path} is missing or not executable: run scripts/setup.sh to build the workspace')
    return path


def write_params_file(node_name: str, params: Mapping[str, object], directory: str | Path) -> Path:
    """Write a ROS 2 params file ``{node_name: {ros__parameters: params}}`` and return its path."""
    path = Path(directory) / f'{node_name.strip("/").replace("/", "_")}_params.yaml'
    path.write_text(yaml.safe_dump({node_name: {'ros__parameters': dict(params)}}))
    return path


class NodeProcess:
    """A node started from its installed executable, with its output captured.

    Use as a context manager so the process is always stopped::

        with NodeProcess('sph_tissue_sim', 'sim_node', params={'n_particles': 300}) as sim:
            sim.wait_for_output(r'ready:', timeout=60)
    """

    def __init__(self, pkg: str, exe: str, args: Iterable[str] = (), ros_args: Iterable[str] = (),
                 params_file: str | Path | Iterable[str | Path] | None = None,
                 params: Mapping[str, object] | None = None,
                 env: Mapping[str, str] | None = None, name: str | None = None,
                 node_name: str | None = None, command: Iterable[str] | None = None) -> None:
        self.pkg, self.exe = pkg, exe
        self.name = name or exe
        self._tmp = tempfile.TemporaryDirectory(prefix=f'{self.name}_')
        # ``command`` starts a node that is not installed (a benchmark's script) the same way
        cmd = [*(command if command is not None else [str(executable(pkg, exe))]), *args]
        extra = list(ros_args)
        # params files in order (a later one overrides an earlier one), then ``params`` over them
        files = ([] if params_file is None else [params_file]
                 if isinstance(params_file, (str, Path)) else list(params_file))
        for path in files:
            extra += ['--params-file', str(path)]
        if params:
            # A params file keyed by '/**' applies to whatever the node is called.
            path = write_params_file(node_name or '/**', params, self._tmp.name)
            extra += ['--params-file', str(path)]
        if extra:
            cmd += ['--ros-args', *extra]
        self.cmd = cmd
        self.env = dict(env) if env is not None else ros_env(
            int(os.environ['ROS_DOMAIN_ID']) if 'ROS_DOMAIN_ID' in os.environ else None)
        self._log_path = Path(self._tmp.name) / 'output.log'
        self._log = None
        self.proc: subprocess.Popen | None = None

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> 'NodeProcess':
        self._log = open(self._log_path, 'wb')
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=self._log,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True, preexec_fn=_die_with_parent)
        return self

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def send_signal(self, sig: int) -> None:
        if self.alive():
            os.killpg(self.proc.pid, sig)

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGINT (as Ctrl-C would), then SIGTERM, then SIGKILL; returns the exit code."""
        if self.proc is None:
            return None
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            if self.proc.poll() is not None:
                break
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                self.proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        rc = self.proc.poll()
        if self._log is not None and not self._log.closed:
            self._log.close()
        return rc

    def wait(self, timeout: float) -> int:
        """Wait for the process to exit by itself; returns its exit code."""
        assert self.proc is not None
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired as exc:
            raise AssertionError(
                f'{self.name} did not exit within {timeout} s; output:\n{self.output()}') from exc

    def __enter__(self) -> 'NodeProcess':
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
        self._tmp.cleanup()

    # -- output --------------------------------------------------------------------------------
    def output(self) -> str:
        if self._log is not None and not self._log.closed:
            self._log.flush()
        try:
            return self._log_path.read_bytes().decode(errors='replace')
        except FileNotFoundError:
            return ''

    def wait_for_output(self, pattern: str, timeout: float = 30.0) -> re.Match:
        """Wait until the output matches ``pattern``; fail with the whole log on timeout or exit."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            match = regex.search(self.output())
            if match:
                return match
            if not self.alive():
                raise AssertionError(f'{self.name} exited (code {self.returncode}) before printing '
                                     f'{pattern!r}; output:\n{self.output()}')
            if time.monotonic() > deadline:
                raise AssertionError(f'{self.name}: {pattern!r} not seen within {timeout} s; '
                                     f'output:\n{self.output()}')
            time.sleep(0.05)


def spin_until(node, predicate: Callable[[], bool], timeout: float, executor=None) -> bool:
    """Spin ``node`` until ``predicate()`` is true or ``timeout`` passes; returns the predicate."""
    import rclpy

    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return predicate()
        if executor is not None:
            executor.spin_once(timeout_sec=0.02)
        else:
            rclpy.spin_once(node, timeout_sec=0.02)
    return True


def wait_for_matching(node, endpoint, count: int = 1, timeout: float = 20.0) -> None:
    """Wait until a publisher has ``count`` subscribers, or a subscription ``count`` publishers."""
    if hasattr(endpoint, 'get_subscription_count'):
        current = endpoint.get_subscription_count
        what = f'subscribers on {endpoint.topic_name}'
    else:
        current = endpoint.get_publisher_count
        what = f'publishers on {endpoint.topic_name}'
    executor = getattr(node, 'executor_for_test', None)
    if not spin_until(node, lambda: current() >= count, timeout, executor=executor):
        raise AssertionError(f'expected {count} {what}, have {current()} after {timeout} s')


class Ticker:
    """Calls :meth:`tick` about every ``period`` seconds on its own thread while in a ``with``
    block (a device stream that never stops); subclasses define ``tick``."""

    period = 0.001

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def tick(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while not self._stop.is_set():
            self.tick()
            time.sleep(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5.0)
