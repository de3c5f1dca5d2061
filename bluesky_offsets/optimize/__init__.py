"""From a calibrated twin to a better beam: targets, the optimizer on the differentiable twin.

The plan that drives the motors there is :func:`plans.optimize.optimize_beam`.
"""

from .optimizer import (
    BeamOptimum,
    DarkStart,
    OptimizeOptions,
    TargetUnreachable,
    bounds,
    moved_names,
    optimize_settings,
    predict,
    prediction_sigma,
)
from .targets import (
    MONOCHROMATOR,
    REFOCUSING,
    Constraints,
    Focus,
    FocusAt,
    MaxTransmission,
    SmallestFocus,
    SpotSize,
    Target,
    focus_from_profiles,
    measured_cost,
    target_from,
)

__all__ = [
    "MONOCHROMATOR", "REFOCUSING", "BeamOptimum", "Constraints", "DarkStart", "Focus", "FocusAt", "MaxTransmission",
    "OptimizeOptions", "SmallestFocus", "SpotSize", "Target", "TargetUnreachable", "bounds", "focus_from_profiles",
    "measured_cost", "moved_names", "optimize_settings", "predict", "prediction_sigma", "target_from",
]
