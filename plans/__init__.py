"""Bluesky plans for offset finding at METRIXS (device-agnostic, bluesky protocols).

* :func:`measure_configurations` — footprints at a list of configurations, reached by
  differences from the current reference; one event per configuration.
* :func:`find_high_ray_configurations` (beamline) and
  :func:`high_ray_configurations_on_model` (twin/surrogate) — configurations whose
  footprint has enough rays (x + y histogram sum > :data:`HIGH_RAY_THRESHOLD` = 0.113 of the source rays).
* :func:`find_beam` — bring the beam onto the screen from a dark start (slits open, the
  sensitive motors scanned upstream first, as an operator does).
* :func:`find_offsets` — run a pluggable offset finder (a :class:`Finder`) on a measurement
  and emit offsets per parameter and the loss as a stream.
"""

from .measure import measure_configurations, scan_configurations
from .motion import (
    MotionError,
    MotorLimitError,
    as_configurations,
    current_configuration,
    resolve_motors,
)
from .offsets import Finder, FinderResult, OffsetResult, find_offsets
from .search import (
    HIGH_RAY_THRESHOLD,
    MIN_CONFIGURATIONS,
    enough_rays,
    find_beam,
    find_high_ray_configurations,
    high_ray_configurations_on_model,
    sample_candidates,
)

__all__ = [
    "HIGH_RAY_THRESHOLD", "MIN_CONFIGURATIONS", "Finder", "FinderResult", "MotionError", "MotorLimitError",
    "OffsetResult",
    "as_configurations", "current_configuration", "enough_rays", "find_beam", "find_high_ray_configurations",
    "find_offsets",
    "high_ray_configurations_on_model", "measure_configurations", "resolve_motors", "sample_candidates",
    "scan_configurations",
]
