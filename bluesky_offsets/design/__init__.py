"""The measurement designed for what it tells about the offsets.

:mod:`.information` gives what a frame at any reachable setting would teach (its Fisher matrix
from the twin's exact Jacobian); :mod:`.choose` draws the candidates and takes the most informative
of those that keep the beam on the screen.  The plan that measures, updates and repeats is
:func:`plans.design.measure_designed`.
"""

from bluesky_offsets.design.choose import (
    CRITERIA,
    DETERMINED,
    PRIOR_SIGMA,
    UNDETERMINED,
    Choice,
    DesignOptions,
    candidate_settings,
    classes,
    criterion_value,
    far_from,
    predicted_sigma,
    prior_precision,
    select,
)
from bluesky_offsets.design.information import FrameInformation, design_spec, frame_information

__all__ = ["CRITERIA", "DETERMINED", "PRIOR_SIGMA", "UNDETERMINED", "Choice", "DesignOptions", "FrameInformation",
           "candidate_settings", "classes", "criterion_value", "design_spec", "far_from", "frame_information",
           "predicted_sigma", "prior_precision", "select"]
