"""The fit worker process: ``python -m mag_calibrator_ros.calibration.fit_worker``.

Reads FitJobs from stdin and writes JobOutcomes to stdout, each a pickle behind an 8-byte
length, until stdin closes (its parent, ``jobs.ProcessRunner``, stopped or died). Started by
the runner, never by users. A plain subprocess rather than multiprocessing: nothing of the
parent's main script is imported again, and the worker cannot outlive its parent.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import struct
import sys
from typing import BinaryIO

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
    from dataclasses import replace

    from mag_calibrator_ros.calibration.jobs import run_job  # the fitting stack, imported once

    while True:
        try:
            job = receive(jobs)
        except EOFError:
            return
        send(outcomes, replace(run_job(job), job=None))  # the parent still holds the job


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the node; it closes our stdin
    with contextlib.suppress(OSError, AttributeError):  # not permitted or not POSIX: run as is
        os.nice(WORKER_NICENESS)
    with contextlib.suppress(OSError, AttributeError):  # not Linux: the niceness alone
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    outcomes, sys.stdout = sys.stdout.buffer, sys.stderr  # nothing printed may reach the pipe
    serve(sys.stdin.buffer, outcomes)


if __name__ == '__main__':
    main()
