"""Recording the pilot's range of motion (state ``rom_limits``): the envelope of the ISB angles.

While the operator moves the pilot's arm through its comfortable range (the robot in minimal
impedance), the loop hands every tick's row to a :class:`RomEnvelope` (it takes the recorder's
place, so nothing extra runs in the tick when no range is being recorded). The envelope keeps
the smallest and largest of each ISB angle; the horizontal rotation only where the elevation is
above ``horizontal_free_below_deg`` (below it the angle is undefined and is not limited, see
:class:`hal.isb.IsbLimits`). The result becomes the pilot's :class:`~hal.isb.IsbLimits`, enforced
by the safety monitor in every state that says ``enforce_isb``.
"""

from __future__ import annotations

import math

import numpy as np

from daror_runtime.data.tick_row import Q_SLICE
from daror_runtime.errors import InputError
from hal.isb import ISB_NAMES, AngleRange, IsbLimits, Shoulder
from hal.robot import N_JOINTS


class RomRecordingError(InputError):
    """The recorded range cannot be used as the pilot's limits (too small, or not recorded)."""


class RomEnvelope:
    """Smallest and largest ISB angles seen; a loop ``Recording`` (``push(row) -> bool``).

    Args:
        shoulder: the robot's shoulder (ISB angles of a configuration, ~1 us).
        horizontal_free_below_rad: the horizontal rotation counts only above this elevation.
    """

    def __init__(self, shoulder: Shoulder, horizontal_free_below_rad: float) -> None:
        self._isb = shoulder.isb_single
        self._free = horizontal_free_below_rad
        self.lower_rad = np.full(N_JOINTS, np.inf)
        self.upper_rad = np.full(N_JOINTS, -np.inf)
        self.samples = 0

    def push(self, row: np.ndarray) -> bool:
        """One loop row (:data:`~daror_runtime.data.tick_row.RECORD_COLUMNS`); NaN rows (no reading) are skipped."""
        q = row[Q_SLICE]
        if not np.all(np.isfinite(q)):
            return True
        angles = self._isb(np.ascontiguousarray(q))
        lower, upper = self.lower_rad, self.upper_rad
        for j in range(N_JOINTS):
            if j == 1 and angles[0] < self._free:
                continue
            value = angles[j]
            if value < lower[j]:
                lower[j] = value
            if value > upper[j]:
                upper[j] = value
        self.samples += 1
        return True

    def limits(self, template: IsbLimits, min_range_deg: float) -> IsbLimits:
        """The recorded range as the pilot's limits (``template`` gives ``horizontal_free_below_deg``).

        Raises:
            RomRecordingError: nothing recorded, or an angle spans less than ``min_range_deg``.
        """
        if self.samples == 0:
            raise RomRecordingError("no range of motion was recorded: start a recording and move the pilot's arm")
        ranges = []
        for j, name in enumerate(ISB_NAMES):
            low, high = math.degrees(self.lower_rad[j]), math.degrees(self.upper_rad[j])
            if not (math.isfinite(low) and math.isfinite(high)):
                raise RomRecordingError(
                    f"{name} was never recorded (the elevation stayed below "
                    f"{template.horizontal_free_below_deg:g} deg); raise the arm and record again"
                )
            if high - low < min_range_deg:
                raise RomRecordingError(
                    f"{name} spans only {high - low:.1f} deg ({low:.1f} to {high:.1f}); at least "
                    f"{min_range_deg:g} deg are needed: move the pilot's arm through its whole range and record again"
                )
            ranges.append(AngleRange(lower_deg=max(low, -180.0), upper_deg=min(high, 180.0)))
        return IsbLimits(
            elevation=ranges[0],
            horizontal_rotation=ranges[1],
            axial_rotation=ranges[2],
            elbow=ranges[3],
            horizontal_free_below_deg=template.horizontal_free_below_deg,
        )
