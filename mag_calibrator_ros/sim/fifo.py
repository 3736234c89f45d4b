# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The ICM-20948's FIFO as the simulator keeps it: a byte queue, each record's truth beside it.

A byte stream, as on the chip: a read pops bytes, not records, so a read that breaks off part way
through a record, a record lost in stream mode's overwrite or a byte that slips leave every later
record misaligned until a reset, as they do on real boards (which is why ArduPilot and PX4 check
and reset it). Each record's truth rides along so a test can tell which samples a driver got
whole, which it lost and which it could only have read torn (``delivered``, ``lost``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from mag_calibrator_ros.icm20948 import registers as reg

JUNK_BYTE = 0xA5  # what a corrupting glitch leaves
DELIVERED_LOG_SIZE = 16384  # truths of records popped whole, newest last (15 s at 1125 Hz)


@dataclass
class _Record:
    remaining: int  # bytes of it still in the FIFO
    truth: object
    whole: bool = True  # no byte of it lost before the host popped it


class SimulatedFifo:
    """Bytes in the FIFO, oldest first. ``write`` appends one record per the mode (snapshot: not
    at all once it would not fit; stream: the oldest bytes make room); ``pop`` serves FIFO_R_W
    reads; ``latch_count`` FIFO_COUNTH. Counts: ``records_written``, ``lost`` (never popped
    whole: dropped, overwritten, reset, slipped) and ``delivered``, the truths of records
    popped whole (a log it may share: the simulator's inertial reads)."""

    def __init__(self, size: int = reg.FIFO_SIZE, delivered: deque | None = None) -> None:
        self.size = size
        self._bytes = bytearray()
        self._records: deque[_Record] = deque()
        self.overflowed = False  # INT_STATUS_2 FIFO_OVERFLOW_INT, cleared by reading it
        self.records_written = 0
        self.lost = 0
        self.delivered = delivered if delivered is not None else deque(
            maxlen=DELIVERED_LOG_SIZE)
        self.delivered_count = 0
        self._latched = 0

    @property
    def count(self) -> int:
        return len(self._bytes)

    def clear(self) -> None:
        """FIFO_RST, or power-on: empty, every record in it lost."""
        self.lost += len(self._records)
        self._bytes.clear()
        self._records.clear()

    def write(self, record: bytes, truth: object, snapshot: bool) -> None:
        """One sample's record at its sample time. Snapshot mode writes nothing once the record
        would not fit (DS-000189 FIFO_MODE: no further writes when full); stream mode writes it
        and the oldest bytes go, a record part way included."""
        if not record:
            return
        self.records_written += 1
        if snapshot and self.count + len(record) > self.size:
            self.overflowed = True
            self.lost += 1
            return
        self._bytes += record
        self._records.append(_Record(len(record), truth))
        excess = self.count - self.size
        if excess > 0:
            self.overflowed = True
            self._drop(excess)

    def overrun(self, records: int) -> None:
        """``records`` samples written while the FIFO had no room for any of them."""
        self.records_written += records
        self.lost += records
        self.overflowed = True

    def latch_count(self) -> int:
        """FIFO_COUNTH read: the count both count registers report until the next latch."""
        self._latched = self.count
        return self._latched

    @property
    def latched_count(self) -> int:
        return self._latched

    def pop(self, length: int) -> list[int]:
        """``length`` FIFO_R_W bytes; past the end, the empty FIFO's byte."""
        taken = min(length, self.count)
        values = list(self._bytes[:taken])
        del self._bytes[:taken]
        while taken > 0:
            head = self._records[0]
            step = min(taken, head.remaining)
            head.remaining -= step
            taken -= step
            if head.remaining == 0:
                self._records.popleft()
                if head.whole:
                    self.delivered.append(head.truth)
                    self.delivered_count += 1
                else:
                    self.lost += 1
        return values + [reg.FIFO_EMPTY_BYTE] * (length - len(values))

    def slip(self, count: int = 1, junk: int = 0) -> None:
        """Fault: ``count`` bytes at the head vanish (a glitch the host never saw), so every
        record after them reads shifted; ``junk`` bytes appear after what is left of the head
        record, so with ``junk == count`` the count stays whole records and only that one
        record is corrupt."""
        self._drop(min(count, self.count))
        if junk and self._records:
            head = self._records[0]
            self._bytes[head.remaining:head.remaining] = bytes([JUNK_BYTE]) * junk
            head.remaining += junk
            head.whole = False

    def _drop(self, count: int) -> None:
        del self._bytes[:count]
        while count > 0:
            head = self._records[0]
            taken = min(count, head.remaining)
            head.remaining -= taken
            head.whole = False
            count -= taken
            if head.remaining == 0:
                self._records.popleft()
                self.lost += 1
