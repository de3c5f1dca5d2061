"""The torch engine: the beamline traced in PyTorch, ray for ray as RAYX traces it, differentiably.

RAYX, the reference engine, has no gradients and no batch interface.  This engine traces the same
beamline element by element in RAYX's conventions, batched over configurations and rays, on CPU or
CUDA, differentiable in every parameter; :class:`TorchEngine` is the twin behind the
:class:`~bluesky_offsets.physics.twin.TraceEngine` interface.

Modules, each importing only those above it:

random_streams
    RAYX's counter-based random stream (Squares) and the fast one's slit kicks.
surfaces
    Hit points, normals and outlines per surface type: plane, quadric, toroid.
compiling
    A batch of parameter vectors (METRIXS or an RML beamline) as tensors: :func:`compile_beamline`.
sampling
    Source rays and every random draw of a trace: :func:`sample_source`, :func:`rays_from_arrays`.
tracing
    The element-by-element trace to the screen: :func:`trace_rays`, :class:`Beam`.
binning
    Histograms, camera profiles, moments and features of a :class:`Beam`.
jacobians
    Exact per-ray Jacobians (:class:`RayJacobian`) and the batched backward pass.
torch_twin
    :class:`TorchEngine` and :class:`TorchOptions`: requests, batches, products, Jacobians.
rml_twin
    :class:`RmlTorchEngine`: the engine on a described beamline's own RML and RAYX's source rays.
"""

from bluesky_offsets.physics.engine.binning import FEATURES, features_from_moments, histograms, moments
from bluesky_offsets.physics.engine.compiling import CompiledBeamline, Optic, compile_beamline
from bluesky_offsets.physics.engine.jacobians import FORWARD_AD, RAY_WEIGHT_FLOOR, RayJacobian
from bluesky_offsets.physics.engine.rml_twin import RmlTorchEngine
from bluesky_offsets.physics.engine.sampling import (Draws, LazyDraws, Rays, SourceUnits, given_units, rays_from_arrays,
                                                     sample_source, source_rays, source_units)
from bluesky_offsets.physics.engine.torch_twin import TorchEngine, TorchOptions, TraceBatch, device_agreement
from bluesky_offsets.physics.engine.tracing import Beam, trace_rays

__all__ = [
    "FEATURES", "FORWARD_AD", "RAY_WEIGHT_FLOOR", "Beam", "CompiledBeamline", "Draws", "LazyDraws", "Optic",
    "RayJacobian", "Rays", "RmlTorchEngine", "SourceUnits", "TorchEngine", "TorchOptions", "TraceBatch",
    "compile_beamline", "device_agreement", "features_from_moments", "given_units", "histograms", "moments",
    "rays_from_arrays", "sample_source", "source_rays", "source_units", "trace_rays",
]
