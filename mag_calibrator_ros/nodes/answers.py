# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Service callbacks that always answer, and one thread for a node's slow work whose results
come back on the executor: a waiting service never blocks the timers that complete it, and an
unexpected error reaches the caller and the log instead of leaving a client waiting forever."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
import inspect
from queue import SimpleQueue
import traceback

from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger


def answering(node: Node, name: str, callback: Callable) -> Callable:
    """A service callback that always answers: an unexpected error fails the call with its
    text (and the traceback in the log)."""

    async def answer(request: Trigger.Request, response: Trigger.Response):
        try:
            result = callback(request, response)
            return await result if inspect.isawaitable(result) else result
        except Exception as error:  # noqa: BLE001 - reported to the caller and the log
            node.get_logger().error(f'{name} failed:\n{traceback.format_exc()}')
            response.success = False
            response.message = f'{name} failed: {type(error).__name__}: {error}'
            return response

    return answer


class IoThread:
    """File loads, saves and the World Magnetic Model on one thread; each result (or the
    exception the work raised, never raised into the executor) completes its Future on the
    executor's thread when ``collect`` runs (the node's poll timer)."""

    def __init__(self, name: str) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._results: SimpleQueue = SimpleQueue()  # (rclpy Future, result) from the thread

    def run(self, work: Callable[[], object]) -> Future:
        """Run ``work`` on the thread; the Future completes with its result or exception."""
        future = Future()

        def run() -> None:
            try:
                result = work()
            except Exception as error:  # noqa: BLE001 - reported, never raised into the executor
                result = error
            self._results.put((future, result))

        self._pool.submit(run)
        return future

    def collect(self) -> None:
        """Complete the Futures of the work done since the last call (on the caller's thread)."""
        while not self._results.empty():
            future, result = self._results.get()
            future.set_result(result)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True)


__all__ = ['IoThread', 'answering']
