# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What fits say about the place and the mounting, kept between fits.

The World Magnetic Model's field here (a location), the latest alignment to the IMU and the
latest check against the model. A new finding (a mounting error, a disturbed field) is warned
about once, not at every refinement. The session notes only fits that passed their own gates
(the model's aside): no other fit says anything about the sensor or the place.
"""

from __future__ import annotations

from dataclasses import replace
import math

from mag_calibrator_ros.calibration.fit.alignment import Alignment
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.earth_field import (
    EarthCheck,
    EarthField,
    EarthReference,
    disturbance_text,
)
from mag_calibrator_ros.calibration.fit.fitting import FitOptions
from mag_calibrator_ros.calibration.live.evidence import Comparison
from mag_calibrator_ros.calibration.live.jobs import JobOutcome
from mag_calibrator_ros.calibration.live.settings import SessionSettings


class Findings:
    """The place and the mounting as the fits so far found them."""

    def __init__(self) -> None:
        self.earth: EarthField | None = None
        """The World Magnetic Model's field here, None while the location is unknown."""
        self.alignment: Alignment | None = None
        """The latest fit's alignment to the IMU (applied or not)."""
        self.earth_check: EarthCheck | None = None
        """The latest fit against the model."""
        self.alignment_warning = ''
        """A mounting error the latest alignment found ('' if none)."""
        self._earth_warning = ''
        self.headroom: tuple[Calibration, Comparison] | None = None
        """The latest refinement that passed its gates, judged against the calibration in force
        then (that calibration, the comparison): how far it is from the best fit of what the
        node holds, which is what ``~/calibrate`` would put in force (report.could_be_better)."""

    def earth_reference(self, settings: SessionSettings, units: str) -> EarthReference | None:
        """The model's field here with the tolerances a fit is checked by."""
        if self.earth is None:
            return None
        return EarthReference(self.earth, units, settings.max_field_error_pct,
                              settings.max_dip_error_deg, settings.earth_field_gate)

    def fit_options(self, settings: SessionSettings, units: str) -> FitOptions:
        """The settings' fit options; with the model's field known (and field_strength 0), the
        target field strength is the model's intensity."""
        options = settings.fit_options()
        if options.field_strength is None and self.earth is not None:
            intensity = self.earth.intensity_in(units)
            if intensity is not None:
                options = replace(options, field_strength=intensity)
        return options

    def note(self, outcome: JobOutcome) -> list[str]:
        """Remember a fit's alignment and model check; the warnings of new findings."""
        warnings = []
        result, current = outcome.result, outcome.job.current
        if (outcome.job.kind == 'refine' and result is not None and result.success
                and outcome.comparison is not None and current is not None):
            self.headroom = (current, outcome.comparison)
        if outcome.alignment is not None:
            self.alignment = alignment = outcome.alignment
            finding = ('' if alignment.success or not math.isfinite(alignment.dip_deg)
                       else alignment.reason)
            if finding and finding.split(':')[0] != self.alignment_warning.split(':')[0]:
                warnings.append(f'alignment to the IMU not applied: {finding}')
            self.alignment_warning = finding
        if outcome.earth_check is not None:
            self.earth_check = outcome.earth_check
            text = disturbance_text(outcome.earth_check)
            if text and not self._earth_warning:
                warnings.append(f'against the World Magnetic Model: {text}')
            self._earth_warning = text
        return warnings

    def earth_warning(self, calibration: Calibration | None, settings: SessionSettings,
                      units: str) -> str:
        """``calibration`` against the model ('' when fine or when nothing can be said)."""
        reference = self.earth_reference(settings, units)
        if reference is None or calibration is None:
            return ''
        check = reference.check(calibration.field_radius(), calibration.metadata_number('dip_deg'))
        return disturbance_text(check)


__all__ = ['Findings']
