# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Test doubles shared by the hardware-layer tests: a clock tests move by hand, and a bus that
records every transaction the driver makes against the simulator."""

from __future__ import annotations

from typing import NamedTuple

from mag_calibrator_ros.icm20948 import registers as reg


class FakeClock:
    """Deterministic time for the simulator and the driver; ``sleep`` advances it."""

    def __init__(self, start: float = 1000.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


class Transaction(NamedTuple):
    time: float
    kind: str  # 'r' byte read, 'w' byte write, 'rb' block read
    address: int
    register: int
    value: int | tuple[int, ...]
    bank: int  # ICM-20948 bank selected when it happened


class RecordingBus:
    """Forwards to ``bus`` and records each transaction with the time and selected bank."""

    def __init__(self, bus, clock: FakeClock, icm_address: int = 0x69) -> None:
        self.bus, self.clock, self.icm_address = bus, clock, icm_address
        self.log: list[Transaction] = []
        self.bank = 0

    def _record(self, kind: str, address: int, register: int, value) -> None:
        self.log.append(Transaction(self.clock.now, kind, address, register, value, self.bank))

    def read_byte_data(self, addr, register):
        value = self.bus.read_byte_data(addr, register)
        self._record('r', addr, register, value)
        return value

    def write_byte_data(self, addr, register, value):
        self.bus.write_byte_data(addr, register, value)
        if addr == self.icm_address and register == reg.REG_BANK_SEL:
            self.bank = value >> reg.BANK_SHIFT
        self._record('w', addr, register, value)

    def read_i2c_block_data(self, addr, register, length):
        values = self.bus.read_i2c_block_data(addr, register, length)
        self._record('rb', addr, register, tuple(values))
        return values
