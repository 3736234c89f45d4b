# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Ctrl-C and SIGTERM end either node cleanly, as `ros2 launch` delivers them (issue #21).

A terminal's Ctrl-C reaches every process of the launch's group and launch then forwards one
more SIGINT, so a node gets two in quick succession; with rclpy's own handlers the second one
was a KeyboardInterrupt inside ``destroy_node``: a traceback and exit -2 ("process has died").
Each node runs here in a process group of its own, as under a terminal, started by its console
script (which catches the signals before the heavy imports: a Ctrl-C during them was a
traceback, issue #46), and gets the signals at different moments: while it imports, while it
builds itself, and once it runs; "SIGINT twice" goes to the whole
group first (the calibrator's fit worker too, which must not print a traceback while it still
imports), then to the node. It must exit 0 without a traceback, and in bounded time.
"""

from concurrent.futures import ThreadPoolExecutor
import os
from pathlib import Path
import random
import signal
import subprocess
import sys
import time

import pytest
from rclpy.exceptions import InvalidHandle

from mag_calibrator_ros.nodes.runtime import LAUNCH_PID_ENV, NodeThreads, wait_until

EXIT_TIMEOUT_S = 30.0
START_TIMEOUT_S = 60.0
NODES = {
    # module, arguments, the log line that says it runs
    'icm20948_driver': ('mag_calibrator_ros.nodes.icm20948_driver', ['-p', 'backend:=sim'],
                        'sim backend, ICM-20948'),
    'mag_calibrator': ('mag_calibrator_ros.nodes.mag_calibrator', [], 'no calibration file at'),
}


def console_script(name: str) -> list[str]:
    """The command a console script runs (``ros2 run``, ``ros2 launch``): its entry in
    nodes/entry.py, which catches the signals before the heavy imports."""
    return [sys.executable, '-c',
            f'import sys; from mag_calibrator_ros.nodes.entry import {name}; sys.exit({name}())']
RUNNING, RANDOM = 'running', 'random'
# When: after the node's start-up line (RUNNING), or this many seconds after its signal handlers
# are set (rclpy.init, building the node, its first spins), or a random such moment in [0, 1).
SIGNALS = {
    'SIGINT twice': (signal.SIGINT, signal.SIGINT),
    'SIGTERM': (signal.SIGTERM,),
    'SIGINT then SIGTERM': (signal.SIGINT, signal.SIGTERM),
}
CASES = [('SIGINT twice', moment, gap) for moment in (0.0, 0.15, 0.5, RANDOM, RUNNING)
         for gap in (0.005, 0.1)] + [
    ('SIGTERM', 0.15, 0.0), ('SIGTERM', RUNNING, 0.0), ('SIGINT then SIGTERM', RUNNING, 0.05)]
CONCURRENT_CASES = 4
"""Cases run at once: each is a process that mostly waits (its start-up, a moment, its exit);
more at once would stretch every start-up, and with it which phase a fixed moment lands in."""


def catches(pid: int, number: int) -> bool:
    """Whether process ``pid`` has a handler for signal ``number`` (Linux: SigCgt in /proc):
    Python itself only catches SIGINT, so a caught SIGTERM means the node's handlers are set."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except FileNotFoundError:
        return False
    (mask,) = [line.split()[1] for line in status.splitlines() if line.startswith('SigCgt:')]
    return bool(int(mask, 16) >> (number - 1) & 1)


def signal_once(tmp_path: Path, name: str, signals: str, moment, gap: float, index: int
                ) -> str | None:
    """One case: start the node in a process group of its own, send it ``signals`` at
    ``moment``, ``gap`` seconds apart. Returns None when it exited 0 without a traceback in
    bounded time, else what went wrong, with its output."""
    if moment == RANDOM:
        moment = random.SystemRandom().uniform(0.0, 1.0)
    _, arguments, running_line = NODES[name]
    case_dir = tmp_path / f'case{index}'
    case_dir.mkdir()
    log_path = case_dir / 'output.log'
    namespace = f'/shutdown_{name}_{index}_{int(time.monotonic() * 1000) % 100000}'
    if name == 'mag_calibrator':
        arguments = arguments + ['-p', f'calibration_file:={case_dir / "calibration.yaml"}']
    command = [*console_script(name), '--ros-args', '-r', f'__ns:={namespace}', *arguments]
    when = f'{name}, {signals} {gap} s apart at {moment}'
    with log_path.open('wb') as log:
        process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log,
                                   stderr=subprocess.STDOUT, start_new_session=True)
        try:
            if not wait_until(lambda: catches(process.pid, signal.SIGTERM), START_TIMEOUT_S,
                              step_s=0.005):
                return f'{when}: no handlers after {START_TIMEOUT_S} s'
            if moment == RUNNING:
                if not wait_until(lambda: running_line in log_path.read_text(errors='replace'),
                                  START_TIMEOUT_S):
                    return f'{when}: not running: {log_path.read_text(errors="replace")}'
            else:
                time.sleep(moment)
            for number_index, number in enumerate(SIGNALS[signals]):
                if number_index == 0 and signals == 'SIGINT twice':
                    os.killpg(process.pid, number)  # the terminal's Ctrl-C
                else:
                    process.send_signal(number)  # launch's
                time.sleep(gap)
            code = process.wait(timeout=EXIT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            code = f'none within {EXIT_TIMEOUT_S} s'
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    output = log_path.read_text(errors='replace')
    if code != 0 or 'Traceback' in output or 'KeyboardInterrupt' in output:
        return f'{when}: exit {code}: {output}'
    return None


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc/<pid>/status')
@pytest.mark.parametrize('name', sorted(NODES))
def test_a_node_ends_cleanly_on_launch_style_signals(tmp_path, name):
    """Every case of CASES, each its own process (own process group, own namespace), a few at
    once: they share nothing but the machine, and a case spends most of its time waiting."""
    with ThreadPoolExecutor(max_workers=CONCURRENT_CASES) as pool:
        failures = [failure for failure in pool.map(
            lambda numbered: signal_once(tmp_path, name, *numbered[1], numbered[0]),
            enumerate(CASES)) if failure is not None]
    assert not failures, '\n\n'.join(failures)


PARENT = '''#!{python}
"""Stands in for the ros2 command line: starts the node as its child and waits, as ros2 run
and ros2 launch do."""
import subprocess, sys, time
child = subprocess.Popen(sys.argv[1:], stdin=subprocess.DEVNULL)
print(child.pid, flush=True)
time.sleep(3600)
'''


def calibrator_under(starter: Path, case_dir: Path, namespace: str) -> list[str]:
    """The calibrator's command as ``starter`` (a stand-in for ros2 run or ros2 launch) runs
    it, with a calibration file of its own in ``case_dir``."""
    module, arguments, _ = NODES['mag_calibrator']
    return [str(starter), sys.executable, '-m', module, '--ros-args', '-r',
            f'__ns:={namespace}', *arguments,
            '-p', f'calibration_file:={case_dir / "calibration.yaml"}']


def ended(pid: int) -> bool:
    """Whether process ``pid`` has exited (gone, or a zombie its starter has not reaped)."""
    return (not Path(f'/proc/{pid}').exists()
            or 'State:\tZ' in Path(f'/proc/{pid}/status').read_text())


def kill_group(pid: int) -> None:
    """SIGKILL the process group led by ``pid`` (the starter and the node in it), if any."""
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def killed_parent(tmp_path: Path, parent_name: str, ends: bool) -> str | None:
    """Start the calibrator under a parent named ``parent_name``, SIGKILL the parent once the
    node runs. Returns None when the node ended (``ends``: within EXIT_TIMEOUT_S, saying why,
    without a traceback) or kept running for 3 s (not ``ends``), else what happened."""
    running_line = NODES['mag_calibrator'][2]
    case_dir = tmp_path / parent_name
    case_dir.mkdir()
    parent = case_dir / parent_name
    parent.write_text(PARENT.format(python=sys.executable))
    parent.chmod(0o755)
    log_path = case_dir / 'output.log'
    command = calibrator_under(
        parent, case_dir, f'/orphan_{parent_name}_{int(time.monotonic() * 1000) % 100000}')
    with log_path.open('wb') as log:
        starter = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                   stderr=log, start_new_session=True)
        node = int(starter.stdout.readline())
        try:
            if not wait_until(lambda: running_line in log_path.read_text(errors='replace'),
                              START_TIMEOUT_S):
                return f'{parent_name}: not running: {log_path.read_text(errors="replace")}'
            starter.kill()
            starter.wait()
            stopped = wait_until(lambda: ended(node), EXIT_TIMEOUT_S if ends else 3.0)
        finally:
            kill_group(starter.pid)  # the node is in the starter's group
    output = log_path.read_text(errors='replace')
    if stopped != ends or (ends and ('ended without stopping it' not in output
                                     or 'Traceback' in output)):
        return f'{parent_name}: {"ended" if stopped else "still running"}: {output}'
    return None


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc/<pid>/cmdline')
def test_a_node_started_by_the_ros2_command_ends_when_that_process_is_killed(tmp_path):
    """A SIGTERM to ``ros2 launch`` ends launch and leaves its nodes running (launch's own
    'using SIGTERM can result in orphaned processes'); a calibrator left so could keep turning
    the robot. A node the ros2 command started stops when that process ends, however it ended
    (here SIGKILL); one started by anything else is not tied to its parent. Both at once: the
    second's 3 s of still running overlap the first's."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        failures = [failure for failure in pool.map(
            lambda case: killed_parent(tmp_path, *case), [('ros2', True), ('supervisor', False)])
            if failure is not None]
    assert not failures, '\n\n'.join(failures)


LAUNCH_GONE = '''#!{python}
"""Stands in for a launch that fails after starting the node (rviz:=true without rviz2): names
its pid as the launch file does, starts the node and exits at once."""
import os, subprocess, sys
os.environ[{variable!r}] = str(os.getpid())
child = subprocess.Popen(sys.argv[1:], stdin=subprocess.DEVNULL)
print(child.pid, flush=True)
'''


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc/<pid>')
def test_a_node_whose_launch_ended_before_the_node_looked_stops_by_itself(tmp_path):
    """`rviz:=true` without rviz2: launch stopped after starting both nodes, before they ran,
    so their parent was already init and nothing tied them to it: orphans publishing for good
    (issue #46). The launch's pid, given in the environment, ties them."""
    starter = tmp_path / 'launch'
    starter.write_text(LAUNCH_GONE.format(python=sys.executable, variable=LAUNCH_PID_ENV))
    starter.chmod(0o755)
    log_path = tmp_path / 'output.log'
    command = calibrator_under(starter, tmp_path, f'/launch_gone_{os.getpid()}')
    with log_path.open('wb') as log:
        process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                   stderr=log, start_new_session=True)
        node = int(process.stdout.readline())
        process.wait()  # the launch is gone before the node has started
        try:
            stopped = wait_until(lambda: ended(node), START_TIMEOUT_S + EXIT_TIMEOUT_S)
        finally:
            kill_group(process.pid)
    output = log_path.read_text(errors='replace')
    assert stopped, output
    assert 'ended without stopping it' in output and 'Traceback' not in output, output


def test_the_console_scripts_catch_the_stop_signals_before_any_heavy_import():
    """What a Ctrl-C during start-up meets: the entry points in nodes/entry.py, which import
    neither rclpy nor numpy before the handlers are set."""
    setup = (Path(__file__).resolve().parents[1] / 'setup.py').read_text()
    for name in NODES:
        assert f"'{name} = {{PACKAGE}}.nodes.entry:{name}'" in setup
    probe = ('import signal, sys; from mag_calibrator_ros.nodes import entry; '
             'entry.catch_stop_signals(); '
             'print(sorted(m for m in ("rclpy", "numpy", "scipy") if m in sys.modules), '
             'type(signal.getsignal(signal.SIGTERM)).__name__)')
    output = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                            check=True).stdout
    assert output.split() == ['[]', 'StopOnSignal']


class _Raises:
    """An executor whose spin meets what rclpy 7.1 raises when another thread shuts it down
    while it handles a task."""

    def __init__(self, error: Exception) -> None:
        self.error = error

    def spin(self) -> None:
        raise self.error


@pytest.mark.parametrize('error', [AttributeError("'NoneType' object has no attribute 'trigger'"),
                                   InvalidHandle('destruction was requested')])
def test_a_spin_thread_ends_quietly_only_when_its_executor_is_being_stopped(error):
    """`make demo` on a loaded machine printed an InvalidHandle traceback from the spin thread
    as it stopped the nodes; anywhere else the error is real and must surface."""
    threads, executor = NodeThreads(context=None), _Raises(error)
    threads._stopping.add(executor)
    threads._spin(executor)
    threads._stopping.discard(executor)
    with pytest.raises(type(error)):
        threads._spin(executor)
