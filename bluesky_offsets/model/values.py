"""The calibrated model's values, apart from how they are fitted.

:class:`ModelState` (normalized offsets and the included effects' values) and
:class:`CalibratedState` (a state with the covariance of the fit that gave it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics import effects as E
from bluesky_offsets.physics.parameters import METRIXS


@dataclass
class ModelState:
    """Normalized offsets (fractions of each range) and included effects with values."""

    offsets: np.ndarray = field(default_factory=lambda: np.zeros(len(METRIXS)))
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    label: str = "twin"

    def with_effect(self, name: str, values: Mapping[str, float] | None = None) -> ModelState:
        """A new model version that includes effect ``name`` (values default to 0 = absent)."""
        eff = E.get(name)
        if name in self.effects:
            raise InputError(f"the model already includes {name!r}")
        return ModelState(self.offsets.copy(), {**self.effects, name: eff.values(values)},
                          f"{self.label} + {name}")

    def vector(self) -> np.ndarray:
        """The normalized offsets, then :meth:`effect_vector`: the parameters a fit moves, in its order."""
        return np.r_[self.offsets, self.effect_vector()]

    def effect_vector(self) -> np.ndarray:
        """The included effects' values as one vector, effect by effect in inclusion order."""
        return np.array([v for name in self.effects for v in self.effects[name].values()], dtype=float)

    def set_effect_vector(self, vec: np.ndarray) -> dict[str, dict[str, float]]:
        """The effects' values read from ``vec`` (in :meth:`effect_vector`'s order), as a new mapping."""
        out: dict[str, dict[str, float]] = {}
        i = 0
        for name, vals in self.effects.items():
            out[name] = {}
            for k in vals:
                out[name][k] = float(vec[i])
                i += 1
        return out

    def effect_parameters(self) -> list[tuple[str, E.EffectParameter]]:
        """The included effects' parameters as ``(effect name, parameter)``, in :meth:`effect_vector`'s order."""
        return [(name, p) for name in self.effects for p in E.get(name).parameters]


@dataclass(frozen=True)
class CalibratedState:
    """A model state and the covariance of the fit that gave it.

    The covariance is over the normalized offsets, then the state's effect parameters,
    ``names`` in that order (None: no uncertainty known).  ``uid``: the run the state comes from.
    ``prior_sigma``: the offsets' Gaussian prior σ the covariance holds, where the fit estimated it
    from the data (:func:`~bluesky_offsets.model.posterior.evidence_spread`); None: the table's.
    """

    state: ModelState
    covariance: np.ndarray | None = None
    names: tuple[str, ...] | None = None
    uid: str | None = None
    prior_sigma: float | None = None

    @classmethod
    def of(cls, model) -> CalibratedState:
        """A :class:`CalibratedState` from a calibrated model, a model state or an analysis.

        ``model``: a :class:`CalibratedState` (itself), a :class:`ModelState` (no covariance) or an
        analysis (``plans.diagnose.Analysis``: its ``calibrated`` model).
        """
        if isinstance(model, cls):
            return model
        if isinstance(model, ModelState):
            return cls(model)
        if hasattr(model, "calibrated"):
            return model.calibrated
        raise TypeError(f"expected a calibrated model, a model state or an analysis, got {type(model).__name__}")
