# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Readings that wait while a fit runs, and the requests that wait for them.

A fit runs on a snapshot of the buffer; the readings that arrive meanwhile are held here in
order and fed to the session afterwards (``CalibrationSession._advance``), so what a fit and the
next one see does not depend on how long the fit took. They are fed a few per call: each costs
about as much as a message, and the callback that feeds them must stay quick. A ``~/calibrate``
fits every reading received before the call, so it waits here until they are all fed.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np

from mag_calibrator_ros.calibration.live.pairing import Pair

HOLD_LIMIT = 5000
"""Readings held while a fit runs; beyond this (a worker far too slow for the rate) the oldest
are fed to the buffer at once and the run is no longer exactly reproducible (counted)."""

DRAIN_PER_MESSAGE = 2
"""Held readings fed per incoming message once a fit is done: bounded work per callback. Each
costs about as much as the message itself, so the callback's worst case stays a few times its
median and the backlog of a fit still shrinks by two readings a message."""

DRAIN_FOR_REQUEST = 64
"""Held readings a poll feeds while a ~/calibrate waits for them (its fit includes every reading
received before the call): a user waits, so the backlog of a slow worker goes first."""


class Reading(NamedTuple):
    """One accepted reading on its way to what it teaches (``CalibrationSession._ingest``):
    through the IMU pairing's wait and, while a fit runs, this backlog."""

    field: np.ndarray
    """Compensated by the compensation in force when it arrived."""
    stamp_ns: int
    epochs: tuple[int, int]
    """(compensation, inputs) epochs on arrival: a newer compensation makes it stale, newer
    inputs make its ``state`` unknown."""
    state: tuple[float, ...] | None
    """The own field's inputs and temperature with it (``CompensationLearner.observe``)."""
    pair: Pair | None = None
    """The accelerometer (and gyroscope) sample paired with it, once decided."""


class Backlog:
    """The held readings (oldest first) and the requests waiting for them."""

    def __init__(self) -> None:
        self._held: deque[Reading] = deque()
        self._requests: deque[tuple[int, int]] = deque()  # (ticket, readings accepted before)
        self.ingested = 0
        """Accepted readings fed to the buffer or the evidence so far (the session counts)."""
        self.overflows = 0

    def __len__(self) -> int:
        return len(self._held)

    def hold(self, item: Reading) -> Reading | None:
        """Hold ``item``; the oldest held one when the backlog is full (feed it now)."""
        overflow = None
        if len(self._held) >= HOLD_LIMIT:
            self.overflows += 1
            overflow = self._held.popleft()
        self._held.append(item)
        return overflow

    def next(self) -> Reading:
        return self._held.popleft()

    def budget(self, flowing: bool) -> int:
        """Held readings a poll feeds: all once messages stopped (nothing else waits), more
        while a request waits for them, a message's few otherwise."""
        if not flowing:
            return HOLD_LIMIT
        return DRAIN_FOR_REQUEST if self._requests else DRAIN_PER_MESSAGE

    def request(self, ticket: int, accepted: int) -> None:
        """A fit asked for once the ``accepted`` readings received so far are fed."""
        self._requests.append((ticket, accepted))

    @property
    def waiting(self) -> bool:
        """Whether a request waits (for its readings, or for the fit running now)."""
        return bool(self._requests)

    @property
    def request_ready(self) -> bool:
        """Whether the oldest request's readings are all fed."""
        return bool(self._requests) and self._requests[0][1] <= self.ingested

    def take_request(self) -> int:
        """The oldest request's ticket (its fit is being made)."""
        return self._requests.popleft()[0]

    def drop_held(self, accepted: int) -> None:
        """Forget the held readings (``~/reset``): requests need not wait for them."""
        self._held.clear()
        self.ingested = accepted


__all__ = ['DRAIN_FOR_REQUEST', 'DRAIN_PER_MESSAGE', 'HOLD_LIMIT', 'Backlog', 'Reading']
