# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Reading the ICM-20948's FIFO: when each record was sampled, and whether it can be trusted.

Pure bookkeeping, no bus: ``Icm20948.read_fifo`` does the transactions. Two jobs:

- ``FifoTimeline``: a record's sample time from the chip's own clock, not from when it was
  read. Records are consecutive samples of one clock, so only where the sequence sits in time
  is unknown; each count read bounds it (the newest record counted was sampled before the count
  was read, the next one after it was asked for). Stamps stay evenly spaced by the chip's
  period, measured over the counts, and move little, and only when the counts say they must.
- ``temperature_plausible``: ArduPilot's corruption sentinel (AP_InertialSensor_Invensensev2
  ``_check_raw_temp``): a record whose temperature word is far from the die's is misaligned
  or corrupt; the die's temperature changes slowly.
"""

from __future__ import annotations

import math

from mag_calibrator_ros.icm20948 import registers as reg

# Temperature words further apart than this are not one die a sample apart: 400 counts, 1.2 degC
# (ArduPilot's bound); a misaligned record's word is any 16 bits.
TEMPERATURE_JUMP_COUNTS = 400
# The die's operating range (DS-000189 table 9, page not verified: -40 to 85 degC) in counts.
TEMPERATURE_RANGE_COUNTS = (
    round((-40.0 - reg.TEMP_OFFSET_C) * reg.TEMP_SENSITIVITY_LSB_PER_C),
    round((85.0 - reg.TEMP_OFFSET_C) * reg.TEMP_SENSITIVITY_LSB_PER_C),
)
# How far the chip's sample clock may run from its nominal period (its own oscillator, as
# ``driver.CLOCK_TOLERANCE``), and how many records apart two counts must be to measure it
# (each middle within half a period: the period then within 0.05 % of itself).
PERIOD_TOLERANCE = 0.10
PERIOD_BASELINE = 1024
# The sequence moves towards the middle of its bounds once it is SETTLE of a period away, by at
# most STEP of a period a count, so stamps stay evenly spaced to STEP while it settles.
SETTLE = 0.01
STEP = 0.02


def temperature_plausible(counts: int, reference: int | None) -> bool:
    """Whether a record's temperature word can be the die's: in its operating range and, given
    the last trusted word, within ``TEMPERATURE_JUMP_COUNTS`` of it."""
    low, high = TEMPERATURE_RANGE_COUNTS
    if not low <= counts <= high:
        return False
    return reference is None or abs(counts - reference) < TEMPERATURE_JUMP_COUNTS


class FifoTimeline:
    """Sample times for the records of one FIFO run (from a reset to the next), in the driver's
    clock. ``stamp(records, before, after)``: the times of ``records`` new records, the newest
    of which was counted by a count read that began at ``before`` and ended at ``after``.
    ``restart()`` after a reset or a lost record: the next count places the sequence anew.

    Every count bounds where the newest record sits; the bounds of all counts so far intersect.
    The sequence is moved towards the middle of that intersection (``SETTLE``, ``STEP``), and
    just inside a count that falls outside it (that count's bounds then start anew). The period
    is the chip's, not the datasheet's: the records counted since the first count over the time
    between the two counts' middles, once ``PERIOD_BASELINE`` records apart (each middle is
    within half a period, so the error shrinks with the baseline)."""

    def __init__(self, period_s: float) -> None:
        self.nominal_period_s = period_s
        self.period_s = period_s
        self._newest: float | None = None
        self._bounds = (0.0, 0.0)  # where the newest may be, relative to where it is put
        self._first: tuple[int, float] | None = None  # (records before it, its middle)
        self._records = 0  # stamped since the restart
        self.moves = 0

    def restart(self) -> None:
        self._newest = self._first = None
        self._records = 0

    def stamp(self, records: int, before: float, after: float,
              complete: bool = True) -> list[float]:
        """``complete`` False: the FIFO had filled up, so the sample after the newest counted
        may have been dropped rather than not yet taken: only the end of the read bounds it."""
        if records <= 0:
            return []
        self._records += records
        if complete:
            self._learn_period((before - self.period_s + after) / 2.0)
        period = self.period_s
        # The newest record counted was sampled by the end of the count read, and the one after
        # it not before the read began (it would have been counted).
        earliest, latest = (before - period if complete else -math.inf), after
        if self._newest is None:
            newest = (earliest + latest) / 2.0 if complete else latest
            low, high = earliest - newest, latest - newest
            move = 0.0
        else:
            newest = self._newest + records * period
            low = max(self._bounds[0], earliest - newest)
            high = min(self._bounds[1], latest - newest)
            if low > high:  # outside what came before: into this count's bounds, least move
                move = latest - newest if newest > latest else max(earliest - newest, 0.0)
                low, high = earliest - newest, latest - newest
            else:
                middle = (low + high) / 2.0 if math.isfinite(low) else high
                move = min(max(middle, -STEP * period), STEP * period) \
                    if abs(middle) > SETTLE * period else 0.0
        if move:
            self.moves += 1
            newest += move
            low, high = low - move, high - move
        self._newest, self._bounds = newest, (low, high)
        return [newest - (records - 1 - i) * period for i in range(records)]

    def _learn_period(self, middle: float) -> None:
        if self._first is None:
            self._first = (self._records, middle)
            return
        counted, since = self._records - self._first[0], middle - self._first[1]
        if counted >= PERIOD_BASELINE:
            nominal = self.nominal_period_s
            self.period_s = min(max(since / counted, nominal * (1.0 - PERIOD_TOLERANCE)),
                                nominal * (1.0 + PERIOD_TOLERANCE))
