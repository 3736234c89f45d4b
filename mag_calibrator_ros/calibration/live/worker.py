"""The fit worker process: ``python -m mag_calibrator_ros.calibration.live.worker``.

Where a FitJob runs: ``InlineRunner`` (here and now: the CLI, tests) or ``ProcessRunner`` (the
node: one worker process). The worker reads FitJobs from stdin and writes JobOutcomes to
stdout, each a pickle behind an 8-byte length, until stdin closes (its parent, the
``ProcessRunner``, stopped or died). Started by
the runner, never by users. A plain subprocess rather than multiprocessing: nothing of the
parent's main script is imported again, and the worker cannot outlive its parent.
"""

from __future__ import annotations

import contextlib
from dataclasses import replace
import os
import pickle
from queue import SimpleQueue
import signal
import struct
import subprocess
import sys
import threading
from typing import BinaryIO, Protocol

from mag_calibrator_ros.calibration.live.jobs import FitJob, JobOutcome, run_job

_LENGTH = struct.Struct('<Q')
# Fits are background work: on a small or busy computer the node's message path must win the
# CPU, so the worker runs at a lower priority (nice(2); 10 gives it about a tenth of a core a
# contended process gets, and all of an idle one) and as SCHED_BATCH (sched(7)): a job written
# to its pipe wakes it without preempting the node that wrote it (at nice 10 alone, Linux's
# EEVDF scheduler let it take the writer's core for 3-4 ms now and then).
WORKER_NICENESS = 10


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


class InlineRunner:
    """Runs each job at once, in the caller's thread: deterministic and simple (CLI, tests)."""

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


class ProcessRunner:
    """Runs jobs in one worker process (this module), started on the first ``start`` or
    ``submit`` and restarted if it dies; a job it was running comes back as an error. A reader
    thread waits on the worker's output, so ``poll`` never blocks."""

    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._outcomes: SimpleQueue = SimpleQueue()
        self._job: FitJob | None = None
        self.restarts = 0

    @property
    def busy(self) -> bool:
        return self._job is not None

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def start(self) -> None:
        """Start the worker now, so the first fit does not wait for its imports."""
        if self._process is not None and self._process.poll() is None:
            return
        environment = dict(os.environ)  # the worker imports what this process imports
        environment['PYTHONPATH'] = os.pathsep.join(path for path in sys.path if path)
        process = subprocess.Popen(
            [sys.executable, '-m', 'mag_calibrator_ros.calibration.live.worker'],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=environment, close_fds=True,
            start_new_session=True,  # a terminal's Ctrl-C is the node's, even during imports
        )
        self._process, self._outcomes = process, SimpleQueue()
        threading.Thread(target=self._read, args=(process, self._outcomes), daemon=True,
                         name='fit worker reader').start()

    @staticmethod
    def _read(process: subprocess.Popen, outcomes: SimpleQueue) -> None:
        while True:
            try:
                outcomes.put(receive(process.stdout))
            except Exception:  # noqa: BLE001 - closed, killed or garbled: the worker is gone
                outcomes.put(_DIED)
                return

    def submit(self, job: FitJob) -> None:
        if self._job is not None:
            raise RuntimeError('a job is already running')
        self.start()
        self._job = job
        try:
            send(self._process.stdin, job)
        except OSError:
            self._outcomes.put(_DIED)

    def poll(self) -> JobOutcome | None:
        if self._job is None or self._outcomes.empty():
            return None
        outcome, job = self._outcomes.get(), self._job
        self._job = None
        if outcome is _DIED:
            code = self._stop()
            self.restarts += 1
            return JobOutcome(job, error=f'fit worker process ended (exit status {code}); a '
                                         'new one starts with the next fit')
        return replace(outcome, job=job)  # the submitted job itself: callers compare by identity

    def _stop(self, timeout_s: float = 2.0) -> int | None:
        process, self._process = self._process, None
        if process is None:
            return None
        for stream in (process.stdin, process.stdout):
            with contextlib.suppress(OSError):
                stream.close()
        try:
            return process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            return process.wait()

    def close(self) -> None:
        """Stop the worker: it finishes a running fit's pipe read and exits on end of input."""
        self._job = None
        self._stop()


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
