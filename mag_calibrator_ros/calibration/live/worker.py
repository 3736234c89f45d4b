# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The fit worker process: ``python -m mag_calibrator_ros.calibration.live.worker``.

Where a FitJob runs: ``InlineRunner`` (here and now: the CLI, tests) or ``ProcessRunner`` (the
node: one worker process). The worker says it is ready once its imports are done, then reads
FitJobs from stdin and writes JobOutcomes to stdout, each a pickle behind an 8-byte length,
until stdin closes (its parent, the ``ProcessRunner``, stopped or died). Started by
the runner, never by users. A plain subprocess rather than multiprocessing: nothing of the
parent's main script is imported again, and the worker cannot outlive its parent.

A watchdog bounds every job: a worker that does not answer within ``JOB_DEADLINE_S`` (hung,
swapped out for good) is killed and restarted, and the job comes back as an error that says so;
one that dies is restarted at once, one stopped (SIGSTOP) after ``STOPPED_GRACE_S``, with or
without a job. While it is gone, stopped or starting again, ``problem`` says so (the node's
/diagnostics ERROR).
"""

from __future__ import annotations

import contextlib
from dataclasses import replace
import math
import os
import pickle
from queue import SimpleQueue
import signal
import struct
import subprocess
import sys
import threading
import time
from typing import BinaryIO, Protocol

from mag_calibrator_ros.calibration.live.jobs import FitJob, JobOutcome, run_job

_LENGTH = struct.Struct('<Q')
# Fits are background work: on a small or busy computer the node's message path must win the
# CPU, so the worker runs at a lower priority (nice(2); 10 gives it about a tenth of a core a
# contended process gets, and all of an idle one) and as SCHED_BATCH (sched(7)): a job written
# to its pipe wakes it without preempting the node that wrote it (at nice 10 alone, Linux's
# EEVDF scheduler let it take the writer's core for 3-4 ms now and then).
WORKER_NICENESS = 10

JOB_DEADLINE_S = 300.0
"""How long the worker may take to answer one job, from when it is ready for it, before it is
killed and restarted. Generous by design, as only a worker that no longer runs at all may reach
it: the largest job (a buffer of 5000 samples, the node's ``buffer_size`` limit, with its
evidence; ``benchmarks/bench_engine.py --speed`` measures the fits) must still answer in a small
fraction of it on a computer many times slower than a desktop that gives the nice worker only a
tenth of a core (WORKER_NICENESS). Meanwhile readings wait (``backlog.py``)."""
STARTUP_DEADLINE_S = 300.0
"""How long a starting worker may take to import the fitting stack and say it is ready (as
generous, for the same reasons)."""
STOPPED_GRACE_S = 10.0
"""How long the worker may stay stopped (SIGSTOP, a debugger: state T or t in /proc/<pid>/stat,
proc(5)) before it is replaced. A stopped process makes no progress on any computer, unlike a
slow one, so this need not be generous; until then ``problem`` says so. Without this a stopped
idle worker left /diagnostics OK until a job reached JOB_DEADLINE_S (issue #47)."""
_STATE_CHECK_S = 1.0  # /proc is read at most this often (poll runs per message)
_READY = 'ready'  # the worker's first message: imports done, reading jobs


def send(stream: BinaryIO, value: object) -> None:
    data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LENGTH.pack(len(data)) + data)
    stream.flush()


def receive(stream: BinaryIO) -> object:
    """The next value; EOFError once the other side has closed."""
    header = stream.read(_LENGTH.size)
    if len(header) < _LENGTH.size:
        raise EOFError('closed')
    (length,) = _LENGTH.unpack(header)
    data = stream.read(length)
    if len(data) < length:
        raise EOFError('closed in the middle of a message')
    return pickle.loads(data)


def serve(jobs: BinaryIO, outcomes: BinaryIO) -> None:
    send(outcomes, _READY)
    while True:
        try:
            job = receive(jobs)
        except EOFError:
            return
        send(outcomes, replace(run_job(job), job=None))  # the parent still holds the job


class FitRunner(Protocol):
    """Runs one job at a time; the session submits, then polls until the outcome is there.
    The outcome's ``job`` is the very object submitted (the session compares its calibrations
    with the one in force by identity)."""

    @property
    def busy(self) -> bool: ...

    def submit(self, job: FitJob) -> None: ...

    def poll(self) -> JobOutcome | None: ...

    def close(self) -> None: ...

    @property
    def problem(self) -> str | None:
        """Why fits cannot run now (the worker is gone or starting again), or None."""

    @property
    def restarts(self) -> int:
        """Workers replaced since the runner started (died, or killed by the watchdog)."""

    @property
    def last_restart(self) -> str:
        """Why the worker was last replaced ('' never)."""


class InlineRunner:
    """Runs each job at once, in the caller's thread: deterministic and simple (CLI, tests)."""

    problem = None  # no worker: nothing to lose or restart
    restarts = 0
    last_restart = ''

    def __init__(self) -> None:
        self._outcome: JobOutcome | None = None

    @property
    def busy(self) -> bool:
        return self._outcome is not None

    def submit(self, job: FitJob) -> None:
        if self._outcome is not None:
            raise RuntimeError('a job is already waiting to be polled')
        self._outcome = run_job(job)

    def poll(self) -> JobOutcome | None:
        outcome, self._outcome = self._outcome, None
        return outcome

    def close(self) -> None:
        self._outcome = None


_DIED = object()  # what the reader thread reports when the worker's pipe closes


class _Worker:
    """One worker process, with the thread that reads its output (outcomes, or _DIED)."""

    def __init__(self) -> None:
        environment = dict(os.environ)  # the worker imports what this process imports
        environment['PYTHONPATH'] = os.pathsep.join(path for path in sys.path if path)
        self.process = subprocess.Popen(
            [sys.executable, '-m', 'mag_calibrator_ros.calibration.live.worker'],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=environment, close_fds=True,
            start_new_session=True,  # a terminal's Ctrl-C is the node's, even during imports
        )
        self.started_at = time.monotonic()
        self.ready_at: float | None = None  # when it said it was ready (the reader sets it)
        self._checked_at, self._stopped_at = -math.inf, None  # ``stopped_for``
        self.outcomes: SimpleQueue = SimpleQueue()
        threading.Thread(target=self._read, daemon=True, name='fit worker reader').start()

    def _read(self) -> None:
        while True:
            try:
                value = receive(self.process.stdout)
            except Exception:  # noqa: BLE001 - closed, killed or garbled: the worker is gone
                self.outcomes.put(_DIED)
                return
            if isinstance(value, str) and value == _READY:
                self.ready_at = time.monotonic()
            else:
                self.outcomes.put(value)

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def stopped_for(self, now: float) -> float:
        """Seconds it has been seen stopped (0 while it runs, or where /proc is not there),
        checked at most every _STATE_CHECK_S."""
        if now - self._checked_at >= _STATE_CHECK_S:
            self._checked_at = now
            try:
                with open(f'/proc/{self.process.pid}/stat', 'rb') as stat:
                    state = stat.read().rsplit(b')', 1)[1].split()[0]  # after '(comm)'
            except (OSError, IndexError):
                state = b'R'
            stopped = state in (b'T', b't')
            self._stopped_at = (self._stopped_at or now) if stopped else None
        return 0.0 if self._stopped_at is None else now - self._stopped_at

    def stop(self, kill: bool, timeout_s: float = 2.0) -> int | None:
        """End the process: killed at once, or given ``timeout_s`` to exit on end of input.

        Its output is closed only once it has ended: the reader thread holds that stream's
        lock while it waits in a read, so closing it before blocked until the worker wrote or
        exited, and a stopped (SIGSTOP) or wedged worker never does: the stop hung for ever,
        its timeout never reached (issue #22)."""
        process = self.process
        if kill:
            process.kill()  # SIGKILL ends a stopped (SIGSTOP) process too
        with contextlib.suppress(OSError):
            process.stdin.close()
        try:
            code = process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
        with contextlib.suppress(OSError):
            process.stdout.close()  # the reader has seen end of input: its lock is free
        return code


class ProcessRunner:
    """Runs jobs in one worker process (this module), started on ``start`` or the first
    ``submit``. A reader thread waits on the worker's output, so ``poll`` never blocks; ``poll``
    is also the watchdog: a worker that died, or that did not answer a job within
    ``deadline_s`` (JOB_DEADLINE_S) of being ready for it, or did not get ready within
    STARTUP_DEADLINE_S, is replaced at once, and a job it was running comes back as an error
    naming why."""

    def __init__(self, deadline_s: float | None = None) -> None:
        self.deadline_s = JOB_DEADLINE_S if deadline_s is None else float(deadline_s)
        self._worker: _Worker | None = None
        self._job: FitJob | None = None
        self._submitted_at = 0.0
        self.restarts = 0
        self.last_restart = ''
        """Why the worker was last replaced ('' never)."""

    @property
    def busy(self) -> bool:
        return self._job is not None

    @property
    def pid(self) -> int | None:
        return None if self._worker is None else self._worker.process.pid

    @property
    def problem(self) -> str | None:
        """The worker is gone (until the next ``poll`` replaces it) or starting again after a
        restart; None while it is up, and during the first start-up (the node's own)."""
        worker = self._worker
        if worker is not None and not worker.alive:
            return (f'the fit worker process ended (exit status {worker.process.returncode}); '
                    'it is being restarted')
        if self.restarts and (worker is None or worker.ready_at is None):
            return (f'the fit worker is restarting (restart {self.restarts}: '
                    f'{self.last_restart}); fits wait until it is up')
        stopped = 0.0 if worker is None else worker.stopped_for(time.monotonic())
        if stopped:
            return (f'the fit worker process {worker.process.pid} is stopped (SIGSTOP or a '
                    f'debugger): fits wait; it is replaced after {STOPPED_GRACE_S:g} s stopped')
        return None

    def start(self) -> None:
        """Start the worker now, so the first fit does not wait for its imports."""
        if self._worker is None or not self._worker.alive:
            self._worker = _Worker()

    def submit(self, job: FitJob) -> None:
        if self._job is not None:
            raise RuntimeError('a job is already running')
        self.start()
        self._job, self._submitted_at = job, time.monotonic()
        try:
            send(self._worker.process.stdin, job)
        except OSError:
            self._worker.outcomes.put(_DIED)

    def poll(self) -> JobOutcome | None:
        """The finished job's outcome, or None; the watchdog's checks on every call."""
        worker = self._worker
        if worker is None:
            return None
        if self._job is not None and not worker.outcomes.empty():
            outcome = worker.outcomes.get()
            if outcome is not _DIED:
                job, self._job = self._job, None
                return replace(outcome, job=job)  # the job itself: callers compare by identity
            code = worker.stop(kill=True)  # its pipe closed: gone, or about to be
            why = f'the fit worker process ended (exit status {code})'
        else:
            why = self._overdue(worker)
            if why is None:
                return None
        self._restart(why)
        job, self._job = self._job, None
        if job is None:
            return None
        return JobOutcome(job, error=f'{why}: restarted; the next fit runs in the new worker')

    def _overdue(self, worker: _Worker) -> str | None:
        """Why the worker must be replaced now (dead, or too slow to start or answer), or
        None."""
        if not worker.alive:
            return f'the fit worker process ended (exit status {worker.process.returncode})'
        now = time.monotonic()
        if worker.stopped_for(now) > STOPPED_GRACE_S:
            return f'the fit worker was stopped for more than {STOPPED_GRACE_S:g} s'
        if worker.ready_at is None:
            if now - worker.started_at > STARTUP_DEADLINE_S:
                return f'the fit worker did not start within {STARTUP_DEADLINE_S:g} s'
        elif self._job is not None and now - max(self._submitted_at, worker.ready_at) > (
                self.deadline_s):
            return f'the fit worker did not answer within {self.deadline_s:g} s'
        return None

    def _restart(self, why: str) -> None:
        """Replace the worker now (killed first if it still runs), and count it."""
        if self._worker is not None:
            self._worker.stop(kill=True)
        self._worker = None
        self.restarts += 1
        self.last_restart = why
        self.start()

    def close(self) -> None:
        """Stop the worker: it finishes a running fit's pipe read and exits on end of input."""
        self._job = None
        if self._worker is not None:
            self._worker.stop(kill=False)
            self._worker = None


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the node; it closes our stdin
    with contextlib.suppress(OSError, AttributeError):  # not permitted or not POSIX: run as is
        os.nice(WORKER_NICENESS)
    with contextlib.suppress(OSError, AttributeError):  # not Linux: the niceness alone
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    outcomes, sys.stdout = sys.stdout.buffer, sys.stderr  # nothing printed may reach the pipe
    serve(sys.stdin.buffer, outcomes)


__all__ = ['FitRunner', 'InlineRunner', 'ProcessRunner', 'receive', 'send', 'serve']


if __name__ == '__main__':
    main()
