# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Process entry points for the nodes: the Jazzy start/spin/shutdown idiom in one place."""

from __future__ import annotations

from collections.abc import Callable, Sequence
import functools
import os
from pathlib import Path
import threading
import time
import traceback

import rclpy
from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException, ShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from mag_calibrator_ros.nodes.signals import (
    StopOnSignal,
    catch_stop_signals,
    ignore_stop_signals,
)

SPIN_TIMEOUT_S = 0.05
LAUNCH_PID_ENV = 'MAG_CALIBRATOR_ROS_LAUNCH_PID'
"""Set by launch/mag_calibrator.launch.py to the launch process's pid: the node stops when that
process is gone, even if it was gone before the node could look at its parent."""


def guarded(node: Node, name: str, callback: Callable) -> Callable:
    """``callback`` that logs an unexpected exception (with its traceback, at most every 5 s)
    instead of letting it end the executor's spin: a node keeps running on bad luck. It has the
    callback's signature, so a subscription callback of two arguments gets the MessageInfo."""

    @functools.wraps(callback)
    def run(*args):
        try:
            return callback(*args)
        except Exception:  # noqa: BLE001 - logged; the node must keep serving
            if node.context.ok():  # not a callback caught by shutdown (Ctrl-C, SIGTERM)
                node.get_logger().error(f'{name} failed:\n{traceback.format_exc()}',
                                        throttle_duration_sec=5.0)
            return None

    return run


def spin_node(node_factory: Callable[[], Node], args: Sequence[str] | None = None, *,
              publish_on_shutdown: bool = False) -> int:
    """Init rclpy, build the node, spin until Ctrl-C, SIGTERM or an external shutdown, clean up.

    A process's whole life: the first SIGINT or SIGTERM stops spinning and every later one is
    ignored until the process has ended. ``ros2 launch`` forwards Ctrl-C to nodes the terminal has
    already sent it to, so a node gets two SIGINTs; rclpy's own handlers turn the second into a
    KeyboardInterrupt inside ``destroy_node``, a traceback and exit -2 (issue #21).
    ``publish_on_shutdown``: the context stays up until the node is destroyed, so
    ``destroy_node`` can still publish (a final zero on cmd_vel); without it the context is shut
    down first, so publishing threads of the node stop at their next publish.
    A node started by the ros2 command line also stops when that process ends (``ros2_parent``).
    Returns a process exit code (0 on a normal stop) so console scripts can ``sys.exit`` it.
    """
    stop = catch_stop_signals()  # before init (and before the imports, by the console scripts)
    parent = ros2_parent()
    if stop.received is not None:  # during the imports: nothing started yet
        ignore_stop_signals()
        return 0
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = node_factory()
        _spin_until(node, stop, parent)
    except (ExternalShutdownException, ShutdownException):
        pass
    finally:
        if not publish_on_shutdown:
            rclpy.try_shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        ignore_stop_signals()
    return 0


def ros2_parent() -> int | None:
    """The pid of the ros2 command line that started this node (``ros2 run``, ``ros2 launch``),
    else None. A SIGTERM (``kill``, ``systemctl stop``) ends either without stopping the node it
    started: launch 3.4's own handler says 'using SIGTERM can result in orphaned processes', and
    ros2run does not forward it; a launch that fails after starting a node (``rviz:=true``
    without rviz2) exits before the node has even looked at its parent. A node left running that
    way could keep turning a robot for ``rotation_timeout``; it stops with that process instead,
    as after Ctrl-C. The package's launch file names its pid in LAUNCH_PID_ENV; otherwise the
    parent counts when it is the ros2 command. A node started by anything else (systemd, a
    shell) is not tied to its parent."""
    stated = os.environ.get(LAUNCH_PID_ENV, '')
    if stated.isdigit() and int(stated) > 1:
        return int(stated)
    parent = os.getppid()
    try:
        command = Path(f'/proc/{parent}/cmdline').read_bytes().split(b'\0')
    except OSError:  # not Linux, or the parent is gone already
        return None
    return parent if any(os.path.basename(word) == b'ros2' for word in command[:2]) else None


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended. It need not be the parent: a launch ``prefix`` (gdb,
    valgrind) stands between the launch and the node."""
    if os.getppid() == pid:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):  # gone, or another user's took its pid
        return True
    try:  # ended, not yet reaped by its own parent
        return Path(f'/proc/{pid}/stat').read_text().rpartition(')')[2].split()[0] == 'Z'
    except (OSError, IndexError):
        return False


def _spin_until(node: Node, stop: StopOnSignal, parent: int | None = None) -> None:
    """Spin ``node`` until ``stop`` has seen a signal, or the ``parent`` process has ended.
    Python runs the handler once the wait returns (the node's timers wake it at least every
    SPIN_TIMEOUT_S)."""
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    try:
        while stop.received is None and node.context.ok():
            if parent is not None and _gone(parent):
                node.get_logger().warning(
                    f'the ros2 command that started this node (pid {parent}) ended without '
                    'stopping it (a SIGTERM to ros2 launch or ros2 run does that, and a launch '
                    'that failed after starting it): stopping')
                break
            executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
    finally:
        executor.remove_node(node)
        executor.shutdown()


class NodeThreads:
    """Spins each node with its own SingleThreadedExecutor on its own thread, in one process.

    Why not one MultiThreadedExecutor: Jazzy's rclpy (7.1.x) re-queues callbacks that no worker
    has started yet (ros2/rclpy#1452, fixed upstream by ros2/rclpy#1547). With the driver at
    100 Hz and the calibrator in one such executor the driver fell far below its rate with a
    core busy; one executor per node keeps its rate with CPU to spare. Callbacks of different
    nodes still run concurrently, and a node is stopped before it is destroyed (no handle
    races).
    """

    def __init__(self, context: Context) -> None:
        self._context = context
        self._spinning: dict[Node, tuple[SingleThreadedExecutor, threading.Thread]] = {}
        self._stopping: set[SingleThreadedExecutor] = set()

    def add(self, node: Node) -> Node:
        executor = SingleThreadedExecutor(context=self._context)
        executor.add_node(node)
        thread = threading.Thread(target=self._spin, args=(executor,), daemon=True,
                                  name=f'spin {node.get_name()}')
        self._spinning[node] = (executor, thread)
        thread.start()
        return node

    def _spin(self, executor: SingleThreadedExecutor) -> None:
        try:
            executor.spin()
        except (ExternalShutdownException, ShutdownException):
            pass
        except (AttributeError, InvalidHandle):
            # rclpy 7.1: a shutdown from another thread while a task (a service coroutine) is
            # being handled leaves the handler a guard condition of None, or one destroyed, to
            # trigger (the second seen on `make demo`'s failure path on a loaded machine)
            if executor not in self._stopping:
                raise

    def remove(self, node: Node) -> None:
        """Stop spinning ``node``, then destroy it."""
        executor, thread = self._spinning.pop(node)
        self._stopping.add(executor)
        executor.shutdown()
        thread.join(timeout=5.0)
        self._stopping.discard(executor)
        node.destroy_node()

    def shutdown(self) -> None:
        for node in list(self._spinning):
            self.remove(node)


def wait_until(condition: Callable[[], bool], timeout_s: float, step_s: float = 0.05) -> bool:
    """Poll ``condition`` every ``step_s`` until it holds or ``timeout_s`` has passed; its last
    answer. A bound on waiting for another thread or process (tests, benchmarks), never a
    timing assertion."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(step_s)
    return condition()
