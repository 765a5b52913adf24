"""Ranging (paper §IV-B): waveforms to times of arrival to distances (pure numpy), one
waveform's two-modality reading (PointRanger), and the ranging calibration of t0 and c with
the stage as a ruler."""

from .calibrate import RangeCal, RangingSetup, fit_range, gate_for, learn_template, range_waveforms
from .matched_filter import MatchedFilter, Template, distance_mm, speed_of_sound_mm_s
from .point import PointRanger
from .procedure import calibrate_range

__all__ = [
    "calibrate_range", "distance_mm", "fit_range", "gate_for", "learn_template", "MatchedFilter",
    "PointRanger", "range_waveforms", "RangeCal", "RangingSetup", "speed_of_sound_mm_s",
    "Template",
]
