"""Helpers for tests that run ROS 2 nodes as separate processes through live topics.

* :func:`ros_env` / :func:`random_domain_id`: an environment with an isolated DDS
  domain (random ``ROS_DOMAIN_ID`` in 1..200, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``),
  the repo on ``PYTHONPATH`` and ROS logs under a temporary directory.
* :class:`NodeProcess`: start a node (``python -m ppoe_ros.nodes.<module> --ros-args ...``)
  or ``ppoe`` subcommand in its own process group; :meth:`NodeProcess.stop` sends
  SIGINT then SIGKILL to the whole group.  Use it as a context manager (or call
  ``stop`` in ``finally``) so no child outlives the test.
* :class:`Probe`: an rclpy node inside the test process, in the same domain, to
  publish inputs and collect outputs with timeouts.
* :func:`write_params_file`: a ``--params-file`` YAML for one node.

Usage::

    env = ros_env(tmp_path)
    with Probe(env) as probe, NodeProcess.node("kinematics_node", env, tmp_path,
                                               params_file=pf) as proc:
        out = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        pub = probe.publisher("/joint_states", JointState)
        probe.wait_for_subscribers(pub, proc)
        ...
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from conftest import REPO

#: environment variable: "1" = NodeProcess.node starts the node inside ``ppoe_container``
CONTAINER_ENV = "PPOE_TEST_CONTAINER"
#: the nodes ``ppoe_container`` runs
CONTAINER_NODES = ("kinematics_node", "fusion_node", "tag_bearing_node", "contact_node")

__all__ = [
    "CONTAINER_ENV",
    "REPO",
    "random_domain_id",
    "ros_env",
    "write_params_file",
    "NodeProcess",
    "Probe",
]


def _worker_domains() -> range:
    """The DDS domain ids this test process may use: 1..200, split between pytest-xdist workers
    (``PYTEST_XDIST_WORKER=gwK`` of ``PYTEST_XDIST_WORKER_COUNT``) so that two tests running at once in two workers
    never share a domain."""
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    size = DOMAIN_IDS // max(count, 1)
    return range(1 + index * size, 1 + (index + 1) * size)


#: DDS domain ids used by the tests (1..200; ids above 232 are not valid with the default port mapping)
DOMAIN_IDS = 200
_DOMAIN_NEXT = [random.SystemRandom().randrange(DOMAIN_IDS)]


def random_domain_id() -> int:
    """A DDS domain id for one test: this worker's ids (:func:`_worker_domains`) in turn from a random start, so that
    a test never reuses the domain of the test just before it (whose processes may still be exiting) and other runs
    on the machine are unlikely to share it."""
    ids = _worker_domains()
    _DOMAIN_NEXT[0] += 1
    return ids[_DOMAIN_NEXT[0] % len(ids)]


def ros_env(tmp_dir: Path | str, domain_id: int | None = None) -> dict[str, str]:
    """Environment for node processes: isolated DDS domain, repo importable, logs in ``tmp_dir``."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random_domain_id() if domain_id is None else domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    env["ROS_LOG_DIR"] = str(Path(tmp_dir) / "ros_log")
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    env["RCUTILS_COLORIZED_OUTPUT"] = "0"
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def write_params_file(path: Path | str, params: Mapping[str, Any], node_name: str = "/**") -> Path:
    """Write ``{node_name: {ros__parameters: params}}`` to ``path`` and return it."""
    path = Path(path)
    path.write_text(yaml.safe_dump({node_name: {"ros__parameters": dict(params)}}, sort_keys=False))
    return path


class NodeProcess:
    """A child process in its own process group, output captured to a log file."""

    def __init__(self, cmd: Sequence[str], env: Mapping[str, str], log_path: Path | str,
                 cwd: Path | str | None = None) -> None:
        self.cmd = list(cmd)
        self.log_path = Path(log_path)
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            self.cmd, env=dict(env), cwd=str(cwd or REPO), stdout=self._log,
            stderr=subprocess.STDOUT, start_new_session=True,
        )

    @classmethod
    def node(cls, module: str, env: Mapping[str, str], tmp_dir: Path | str,
             params: Mapping[str, Any] | None = None, params_file: Path | str | None = None,
             name: str | None = None) -> NodeProcess:
        """Start ``ppoe_ros.<module>`` with ``--ros-args`` parameters (``-p k:=v``) and/or a params file; with
        ``PPOE_TEST_CONTAINER=1`` in the test's environment a node of ``ppoe_container`` runs it instead, alone in
        that process (``test/test_container.py`` runs the node tests so)."""
        cmd = [sys.executable, "-m", f"ppoe_ros.nodes.{module}", "--ros-args"]
        if os.environ.get(CONTAINER_ENV) == "1" and module in CONTAINER_NODES:
            cmd = [sys.executable, "-m", "ppoe_ros.nodes.container", module, "--ros-args"]
        if params_file is not None:
            cmd += ["--params-file", str(params_file)]
        for k, v in (params or {}).items():
            cmd += ["-p", f"{k}:={_param_text(v)}"]
        return cls(cmd, env, Path(tmp_dir) / f"{name or module}.log")

    @classmethod
    def ppoe(cls, args: Sequence[str], env: Mapping[str, str], tmp_dir: Path | str,
             name: str) -> NodeProcess:
        """Start ``python -m ppoe_ros.cli <args>`` (the ``ppoe`` entry point)."""
        return cls([sys.executable, "-m", "ppoe_ros.cli", *args], env, Path(tmp_dir) / f"{name}.log")

    def alive(self) -> bool:
        """True while the process runs."""
        return self.proc.poll() is None

    def output(self) -> str:
        """Everything the process wrote so far (stdout + stderr)."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait(self, timeout: float) -> int:
        """Wait for the process to exit by itself; return its code (kills it on timeout)."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"{self.cmd} did not exit within {timeout} s:\n{self.output()[-3000:]}") from None

    def stop(self, timeout: float = 5.0) -> int | None:
        """SIGINT the process group, then SIGKILL after ``timeout`` s; return the exit code."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.proc.wait(timeout=5)
        else:  # the leader exited: make sure nothing of its group is left
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        self._log.close()
        return self.proc.returncode

    def __enter__(self) -> NodeProcess:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def _param_text(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_param_text(x) for x in v) + "]"
    return str(v)


class Probe:
    """An rclpy node in the test process, on the domain of ``env``, to drive and observe nodes."""

    def __init__(self, env: Mapping[str, str], name: str = "test_probe") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ.pop("ROS_LOCALHOST_ONLY", None)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=int(env["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def publisher(self, topic: str, msg_type: Any, qos: Any = 100) -> Any:
        """Create a publisher (default reliable depth 100)."""
        return self.node.create_publisher(msg_type, topic, qos)

    def collect(self, topic: str, msg_type: Any, qos: Any = 1000) -> list[Any]:
        """Subscribe ``topic``; returns the list that received messages are appended to."""
        box: list[Any] = []
        self.node.create_subscription(msg_type, topic, box.append, qos)
        return box

    def spin_for(self, seconds: float) -> None:
        """Process callbacks for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.02, max(0.0, end - time.monotonic())))

    def spin_until(self, pred: Callable[[], bool], timeout: float,
                   proc: NodeProcess | None = None, what: str = "condition") -> None:
        """Spin until ``pred()`` is true; AssertionError (with the node's log) after ``timeout`` s."""
        end = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > end:
                log = proc.output()[-4000:] if proc is not None else ""
                raise AssertionError(f"timeout after {timeout} s waiting for {what}\n--- node log ---\n{log}")
            if proc is not None and not proc.alive():
                raise AssertionError(f"node exited (code {proc.proc.returncode}) while waiting for "
                                     f"{what}\n--- node log ---\n{proc.output()[-4000:]}")
            self.executor.spin_once(timeout_sec=0.02)

    def wait_for_subscribers(self, pub: Any, proc: NodeProcess | None = None, n: int = 1,
                             timeout: float = 45.0, settle: float = 0.5) -> None:
        """Wait until ``pub`` has ``n`` matched subscriptions (the node under test is up).

        The publisher sees the match before the subscriber has matched the publisher
        (discovery is asymmetric), and a best-effort subscriber drops what arrives
        before; so spin ``settle`` seconds more.
        """
        self.spin_until(lambda: pub.get_subscription_count() >= n, timeout, proc,
                        f"a subscriber on {pub.topic_name}")
        self.spin_for(settle)

    def call(self, client: Any, request: Any, proc: NodeProcess | None = None, timeout: float = 60.0,
             settle: float = 1.0, resend_after: float | None = None) -> Any:
        """Call a service once it is ready; return its answer (AssertionError with the node's log after ``timeout``).

        ``service_is_ready`` is the client's view of discovery: the server's response writer may not have
        matched the client's reader yet, and Fast DDS then drops the answer after 100 ms ("failed to send
        response (timeout)"), which a loaded machine reaches. So spin ``settle`` seconds first; an idempotent
        service may also be asked again every ``resend_after`` seconds without an answer.
        """
        self.spin_until(client.service_is_ready, 60, proc, f"service {client.srv_name}")
        self.spin_for(settle)
        end = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            wait = timeout if resend_after is None else min(resend_after, max(0.0, end - time.monotonic()))
            try:
                self.spin_until(future.done, wait, proc, f"the answer of {client.srv_name}")
                return future.result()
            except AssertionError:
                if resend_after is None or time.monotonic() >= end:
                    raise
                client.remove_pending_request(future)

    def wait_for_publishers(self, topic: str, proc: NodeProcess | None = None, n: int = 1,
                            timeout: float = 45.0) -> None:
        """Wait until ``topic`` has ``n`` publishers."""
        self.spin_until(lambda: self.node.count_publishers(topic) >= n, timeout, proc,
                        f"a publisher on {topic}")

    def close(self) -> None:
        """Destroy the node and shut the context down."""
        try:
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            self.context.try_shutdown()

    def __enter__(self) -> Probe:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
