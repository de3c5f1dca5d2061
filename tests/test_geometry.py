"""World frames from our own chain geometry against RAY-UI's, and the RML round trip."""

import math
from pathlib import Path

import numpy as np
import pytest

from bluesky_offsets.physics.geometry import ChainLink, Misalignment, chain_frames, ellipsoid_tangent_angle, misalign
from bluesky_offsets.physics.metrixs import build_beamline, nominal_beamline
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.rml import WORLD_KEYS, RmlError, read_rml, read_world_vectors

SHARED = Path(__file__).resolve().parent / "data" / "reference"  # provenance: its README.md
METRIXS_RML = SHARED / "METRIX_U41_G1_H1_318eV_PS_MLearn_1.15.rml"
RAYUI_FILES = sorted((SHARED / "rayui-misalignment").glob("*.rml"))


def _compare(frames, names, ref):
    for name, frame in zip(names, frames):
        r = ref[name]
        np.testing.assert_allclose(frame.position, r["worldPosition"], rtol=0, atol=1e-6, err_msg=name)
        for key, vec in zip(WORLD_KEYS[1:], (frame.x, frame.y, frame.z)):
            np.testing.assert_allclose(vec, r[key], rtol=0, atol=1e-9, err_msg=f"{name} {key}")


def test_metrixs_nominal_frames_match_reference_rml():
    """Our METRIXS definition, all misalignments zero, reproduces the RML's world vectors."""
    bl = build_beamline(METRIXS.reference)
    _compare(bl.frames(), [o.name for o in bl.objects], read_world_vectors(METRIXS_RML))


@pytest.mark.parametrize("path", RAYUI_FILES, ids=lambda p: p.stem)
def test_misaligned_frames_match_rayui(path):
    """From the alignmentError values alone we recompute RAY-UI's misaligned world frames."""
    bl = read_rml(path)
    assert any(not o.misalignment.is_zero() for o in bl.objects)
    _compare(bl.frames(), [o.name for o in bl.objects], read_world_vectors(path))


def test_rotation_order_and_translation_frame():
    nominal = chain_frames([ChainLink(is_source=True), ChainLink(distance=100.0, theta_in=0.1, theta_out=0.1)])[1]
    mis = Misalignment(tx=1.0, ty=2.0, tz=3.0, rx=1.0, ry=2.0, rz=3.0)
    w = misalign(nominal, mis)
    o = nominal.orientation
    # O_w = O . Rz(rz) . Ry(ry) . Rx(rx), active right-handed rotations in rad
    c, s = math.cos, math.sin
    rx = np.array([[1, 0, 0], [0, c(1e-3), -s(1e-3)], [0, s(1e-3), c(1e-3)]])
    ry = np.array([[c(2e-3), 0, s(2e-3)], [0, 1, 0], [-s(2e-3), 0, c(2e-3)]])
    rz = np.array([[c(3e-3), -s(3e-3), 0], [s(3e-3), c(3e-3), 0], [0, 0, 1]])
    assert np.allclose(w.orientation, o @ rz @ ry @ rx, atol=1e-15)
    assert np.allclose(w.position, nominal.position + w.orientation @ mis.translation)
    assert np.allclose(w.orientation.T @ w.orientation, np.eye(3))


def test_ellipsoid_frame_pitch_equals_mirror_frame_pitch():
    """A pure pitch (rx) is the same in RAY-UI's mirror and ellipsoid frames; yaw is not."""
    nominal = chain_frames([ChainLink(is_source=True), ChainLink(distance=10.0, theta_in=0.03, theta_out=0.03)])[1]
    tau = 0.0317
    pitch = Misalignment(rx=1.0)
    assert np.allclose(misalign(nominal, pitch).orientation, misalign(nominal, pitch, tau).orientation)
    yaw = Misalignment(ry=1.0)
    assert not np.allclose(misalign(nominal, yaw).orientation, misalign(nominal, yaw, tau).orientation)
    lift = Misalignment(ty=1.0)
    d = misalign(nominal, lift, tau).position - nominal.position
    assert np.isclose(np.linalg.norm(d), 1.0) and np.isclose(d @ nominal.y, math.cos(tau))


def test_an_ellipsoid_frame_is_differentiable_in_its_misalignment():
    """A differentiable yaw in an ellipsoid's tilted frame (a float ``tau``, as a described
    beamline's ellipsoid has) stays a tensor with its gradient, equal to the numpy frame."""
    torch = pytest.importorskip("torch")
    nominal = chain_frames([ChainLink(is_source=True), ChainLink(distance=10.0, theta_in=0.03, theta_out=0.03)])[1]
    tau, yaw = 0.0317, torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    w = misalign(nominal, Misalignment(ry=yaw, ty=0.5), tau)
    assert torch.is_tensor(w.orientation) and torch.is_tensor(w.position)
    ref = misalign(nominal, Misalignment(ry=1.0, ty=0.5), tau)
    np.testing.assert_allclose(w.orientation.detach().numpy(), ref.orientation, atol=1e-15)
    (g,) = torch.autograd.grad(w.orientation[0, 2], yaw)
    step = misalign(nominal, Misalignment(ry=1.0 + 1e-6, ty=0.5), tau).orientation[0, 2]
    assert float(g) == pytest.approx((step - ref.orientation[0, 2]) / 1e-6, rel=1e-4)


def test_metrixs_ellipsoid_tangent_angles():
    # The tilt follows from the ellipse RAYX builds (half-axes + design angle); it agrees with
    # atan(tan(theta) (p - q) / (p + q)) at the design angle to the precision of the RML's numbers.
    for name, p, q in (("E1", 39600.0, 1900.0), ("E2", 7750.0, 1000.0)):
        obj = nominal_beamline()[name]
        theta = math.radians(obj.get_float("designGrazingIncAngle"))
        tau = ellipsoid_tangent_angle(obj.get_float("longHalfAxisA"), obj.get_float("shortHalfAxisB"),
                                      theta, p, q)
        assert tau == pytest.approx(math.atan(math.tan(theta) * (p - q) / (p + q)), rel=5e-3)
        assert obj.chain_link().tau == tau


def test_parameters_reach_the_rml():
    v = METRIXS.from_mapping({"E1.rotationXerror": 1.0, "ASBL.totalWidth": 1.95, "E2.longHalfAxisA": 4400.0})
    bl = build_beamline(v, overrides={"ImagePlane": {"translationZerror": 5.0}}, n_rays=1234)
    assert bl["E1"].misalignment.rx == 1.0
    assert bl["ASBL"].get_float("openingWidth") == 1.95
    assert bl["E2"].get_float("longHalfAxisA") == 4400.0
    assert bl["ImagePlane"].misalignment.tz == 5.0
    assert bl["U41_318eV"].get_float("numberRays") == 1234
    xml = bl.to_xml()
    assert xml.count("<object ") == 10 and 'name="ImagePlane"' in xml
    nominal_ip = nominal_beamline().frames()[-1]
    moved = bl.frames()[-1]
    assert np.allclose(moved.position - nominal_ip.position, 5.0 * nominal_ip.z)


def test_bad_overrides_are_refused():
    with pytest.raises(RmlError, match="unknown object 'E3'"):
        build_beamline(METRIXS.reference, overrides={"E3": {"translationZerror": 1}})
    with pytest.raises(RmlError, match="no field 'bogus'"):
        build_beamline(METRIXS.reference, overrides={"E1": {"bogus": 1}})
    with pytest.raises(RmlError, match="source .* has no translationZerror"):
        build_beamline(METRIXS.reference, overrides={"U41_318eV": {"translationZerror": 1}})
