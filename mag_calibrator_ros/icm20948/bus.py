# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""I2C accounting: every transaction, every failure and the bytes it put on the wire.

The driver talks to the chip only through ``CountingBus``, so the error counter in diagnostics
counts what really failed (bring-up retries included), the benchmark's bus share is measured
rather than estimated, and a failing identity check can tell "nothing answers" from "the device
answers, but the bus is unreliable" by what the same address did recently.

Wire cost (7-bit address, SMBus protocols as i2c-dev issues them; 9 bit times per byte with the
ACK, plus one per START, repeated START and STOP):
read byte = S addr reg Sr addr data P (4 bytes, 39 bits); block read of n = (3 + n) bytes,
9 (3 + n) + 3 bits; write byte = S addr reg data P (3 bytes, 29 bits); a failed transaction is
counted as its address byte (S addr P, 11 bits).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, TypeVar

RECENT_TRANSACTIONS = 100  # per address: the failure share quoted in messages
# A device counts as answering while any of its last this-many transactions succeeded: 20
# consecutive failures are a gone device, not noise (0.08 % of the time even at 70 % errors).
ANSWERING_WINDOW = 20

_Result = TypeVar('_Result')


class SmbusLike(Protocol):
    """The subset of ``smbus2.SMBus`` the driver relies on."""

    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]: ...


@dataclass(frozen=True)
class BusCounters:
    """Cumulative totals; subtract two snapshots for a window."""

    transactions: int = 0
    errors: int = 0
    wire_bytes: int = 0
    bits: int = 0

    def __sub__(self, other: BusCounters) -> BusCounters:
        return BusCounters(self.transactions - other.transactions, self.errors - other.errors,
                           self.wire_bytes - other.wire_bytes, self.bits - other.bits)


class BusMonitor:
    """Totals and per-address recent outcomes; outlives any one opened bus (re-opened after a
    fault), so counts and the "answered recently" memory survive re-initialisation.

    Shares: the wire cost of one sensor, measured apart from the rest: whole successful
    transactions to an address in ``labels``, plus parts of transactions a driver ``attribute``s
    (bytes a burst carries for another sensor: issue #11's magnetometer cost)."""

    def __init__(self, labels: dict[int, str] | None = None) -> None:
        self._labels = dict(labels or {})
        self._shares: dict[str, list[int]] = {}
        self._transactions = 0
        self._errors = 0
        self._wire_bytes = 0
        self._bits = 0
        self._recent: dict[int, deque[bool]] = {}

    def record(self, address: int, ok: bool, wire_bytes: int, bits: int) -> None:
        self._transactions += 1
        self._wire_bytes += wire_bytes
        self._bits += bits
        if not ok:
            self._errors += 1
        elif address in self._labels:
            self.attribute(self._labels[address], wire_bytes, bits)
        self._recent.setdefault(address, deque(maxlen=RECENT_TRANSACTIONS)).append(ok)

    @property
    def counters(self) -> BusCounters:
        return BusCounters(self._transactions, self._errors, self._wire_bytes, self._bits)

    def attribute(self, label: str, wire_bytes: int, bits: int) -> None:
        """Count ``wire_bytes`` / ``bits`` already recorded as part of ``label``'s share."""
        share = self._shares.setdefault(label, [0, 0])
        share[0] += wire_bytes
        share[1] += bits

    def share(self, label: str) -> BusCounters:
        """Cumulative wire bytes and bits attributed to ``label`` (transactions/errors 0)."""
        wire_bytes, bits = self._shares.get(label, (0, 0))
        return BusCounters(0, 0, wire_bytes, bits)

    def recent(self, address: int) -> tuple[int, int]:
        """(transactions, failures) among the last ``RECENT_TRANSACTIONS`` to ``address``."""
        outcomes = self._recent.get(address, ())
        return len(outcomes), sum(1 for ok in outcomes if not ok)

    def answering(self, address: int) -> bool:
        """Whether ``address`` acknowledged any of its last ``ANSWERING_WINDOW`` transactions."""
        outcomes = self._recent.get(address, ())
        return any(list(outcomes)[-ANSWERING_WINDOW:])


class CountingBus:
    """An smbus2-like bus that records every transaction in a ``BusMonitor``."""

    def __init__(self, bus: SmbusLike, monitor: BusMonitor | None = None) -> None:
        self.raw = bus
        self.monitor = monitor if monitor is not None else BusMonitor()

    def _call(self, address: int, wire_bytes: int, bits: int,
              operation: Callable[[], _Result]) -> _Result:
        try:
            result = operation()
        except OSError:
            self.monitor.record(address, False, 1, 11)
            raise
        self.monitor.record(address, True, wire_bytes, bits)
        return result

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        return self._call(i2c_addr, 4, 39, lambda: self.raw.read_byte_data(i2c_addr, register))

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        self._call(i2c_addr, 3, 29,
                   lambda: self.raw.write_byte_data(i2c_addr, register, value))

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]:
        return self._call(
            i2c_addr, 3 + length, 9 * (3 + length) + 3,
            lambda: self.raw.read_i2c_block_data(i2c_addr, register, length),
        )

    def close(self) -> None:
        close = getattr(self.raw, 'close', None)
        if close is not None:
            close()
