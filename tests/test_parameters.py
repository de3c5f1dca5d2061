"""The parameter table: one source of truth, conversions, clear errors."""

import numpy as np
import pytest

from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterError, ParameterTable

PAPER_RANGES = {  # paper Table 1 / authors' dataset config
    "U41_318eV.translationXerror": (-0.25, 0.25), "U41_318eV.translationYerror": (-0.25, 0.25),
    "U41_318eV.rotationXerror": (-0.05, 0.05), "U41_318eV.rotationYerror": (-0.05, 0.05),
    "ASBL.totalWidth": (1.9, 2.1), "ASBL.totalHeight": (0.9, 1.1),
    "ASBL.translationXerror": (-0.2, 0.2), "ASBL.translationYerror": (-0.2, 0.2),
    "M1_Cylinder.radius": (174.06, 174.36), "M1_Cylinder.rotationXerror": (-0.25, 0.25),
    "M1_Cylinder.rotationYerror": (-1, 1), "M1_Cylinder.rotationZerror": (-1, 1),
    "M1_Cylinder.translationXerror": (-1, 1), "M1_Cylinder.translationYerror": (-1, 1),
    "SphericalGrating.radius": (109741, 109841), "SphericalGrating.rotationYerror": (-1, 1),
    "SphericalGrating.rotationZerror": (-2.5, 2.5), "ExitSlit.totalHeight": (0.009, 0.011),
    "ExitSlit.translationZerror": (-150, 150), "ExitSlit.rotationZerror": (-0.3, 0.3),
    "E1.longHalfAxisA": (20600, 20900), "E1.shortHalfAxisB": (300.7217, 304.7217),
    "E1.rotationXerror": (-1.5, 1.5), "E1.rotationYerror": (-7.5, 7.5), "E1.rotationZerror": (7, 14),
    "E1.translationYerror": (-1, 1), "E1.translationZerror": (-1, 1),
    "E2.longHalfAxisA": (4325, 4425), "E2.shortHalfAxisB": (96.1561, 98.1561),
    "E2.rotationXerror": (-0.5, 0.5), "E2.rotationYerror": (-7.5, 7.5), "E2.rotationZerror": (22, 32),
    "E2.translationYerror": (-1, 1), "E2.translationZerror": (-1, 1),
}
FIXED = {"M1_Cylinder.radius", "SphericalGrating.radius", "E1.longHalfAxisA", "E1.shortHalfAxisB",
         "E2.longHalfAxisA", "E2.shortHalfAxisB"}


def test_table_matches_paper():
    assert len(METRIXS) == 34
    assert {p.name: (p.low, p.high) for p in METRIXS} == PAPER_RANGES
    assert set(METRIXS.fixed_names) == FIXED
    assert len(METRIXS.motorized_names) == 28
    assert len({p.device for p in METRIXS}) == 34


def test_normalize_roundtrip():
    rng = np.random.default_rng(0)
    x = METRIXS.sample_uniform(100, rng)
    n = METRIXS.normalize(x)
    assert n.min() >= 0 and n.max() <= 1
    np.testing.assert_allclose(METRIXS.denormalize(n), x, rtol=1e-12)
    np.testing.assert_allclose(METRIXS.normalize(METRIXS.low), 0)
    np.testing.assert_allclose(METRIXS.normalize(METRIXS.high), 1)


def test_offsets():
    rng = np.random.default_rng(1)
    off = METRIXS.sample_offsets(rng, size=50)
    assert np.abs(off).max() <= MAX_OFFSET
    phys = METRIXS.offsets_to_physical(off)
    np.testing.assert_allclose(METRIXS.offsets_to_normalized(phys), off)
    np.testing.assert_allclose(phys[:, METRIXS.index("ExitSlit.translationZerror")],
                               off[:, METRIXS.index("ExitSlit.translationZerror")] * 300)
    too_big = np.zeros(34)
    too_big[METRIXS.index("E1.rotationXerror")] = 0.3
    with pytest.raises(ParameterError, match="E1.rotationXerror"):
        METRIXS.offsets_to_physical(too_big)


def test_a_model_stands_at_its_configuration_plus_its_offsets_held_within_bounds():
    here = METRIXS.denormalize(np.full(34, 0.5))
    past = np.zeros(34)
    past[METRIXS.index("E1.rotationXerror")] = MAX_OFFSET + 1e-9  # a fit's rounding past the bound
    vals = METRIXS.model_values(np.stack([here, here]), np.stack([past, -past]))
    i = METRIXS.index("E1.rotationXerror")
    np.testing.assert_allclose(vals[:, i] - here[i], [MAX_OFFSET * METRIXS.span[i], -MAX_OFFSET * METRIXS.span[i]])
    np.testing.assert_array_equal(np.delete(vals, i, axis=1), np.delete(np.stack([here, here]), i, axis=1))


@pytest.mark.parametrize("bad, match", [
    (np.zeros(33), "34 parameters"),
    (np.zeros((2, 35)), "34 parameters"),
    ("abc", "cannot convert|34 parameters"),
])
def test_malformed_vectors(bad, match):
    with pytest.raises(ParameterError, match=match):
        METRIXS.validate(bad)


def test_nan_names_parameter():
    v = METRIXS.reference.copy()
    v[METRIXS.index("E2.rotationYerror")] = np.nan
    with pytest.raises(ParameterError, match="E2.rotationYerror"):
        METRIXS.normalize(v)


def test_unknown_name_and_mapping():
    with pytest.raises(ParameterError, match="unknown parameter 'E3.rotationXerror'"):
        METRIXS.from_mapping({"E3.rotationXerror": 1.0})
    with pytest.raises(ParameterError, match="E2.rotationXerror.*not finite"):
        METRIXS.from_mapping({"E2.rotationXerror": float("inf")})
    v = METRIXS.from_mapping({"E2.rotationXerror": 0.25})
    assert v[METRIXS.index("E2.rotationXerror")] == 0.25
    assert METRIXS.to_mapping(v)["E2.rotationXerror"] == 0.25


def test_outside_box_reports_extrapolation():
    # the reference RML itself lies outside the box in four parameters
    assert set(METRIXS.outside_box(METRIXS.reference)) == {
        "ASBL.totalHeight", "ExitSlit.totalHeight", "E1.rotationZerror", "E2.rotationZerror"}
    assert METRIXS.outside_box(0.5 * (METRIXS.low + METRIXS.high)) == []


def test_version_and_diff():
    changed = ParameterTable([p if p.name != "E1.rotationXerror" else
                              type(p)(**{**p.__dict__, "high": 2.0}) for p in METRIXS])
    assert changed.version != METRIXS.version
    problems = METRIXS.diff(changed.fingerprint())
    assert len(problems) == 1 and "E1.rotationXerror" in problems[0]
    assert METRIXS.diff(METRIXS.fingerprint()) == []


def test_motor_travel_is_the_box_except_for_the_slit_openings():
    from bluesky_offsets.model.diagnosis import OPEN_APERTURE, in_box, open_aperture
    from sim_iocs.metrixs import axis_settings

    wider = {p.name for p in METRIXS if p.limits != (p.low, p.high)}
    assert wider == {"ASBL.totalWidth", "ASBL.totalHeight", "ExitSlit.totalHeight"}
    for p in METRIXS:
        lo, hi = p.limits
        assert lo <= p.low < p.high <= hi and lo > 0 if p.name in wider else (lo, hi) == (p.low, p.high)
    s = axis_settings(METRIXS["ExitSlit.totalHeight"], 0.01)
    assert (s.low, s.high) == (0.005, 0.2)  # the IOC's soft limits: real runs open it to 100 µm
    mid = 0.5 * (METRIXS.low + METRIXS.high)
    opened = open_aperture(np.stack([mid, mid]))
    assert opened.shape == (2, len(METRIXS)) and in_box(mid).all() and not in_box(opened).any()
    assert all((opened[:, METRIXS.index(n)] == v).all() for n, v in OPEN_APERTURE.items())
    assert set(METRIXS.outside_box(opened[0])) == set(OPEN_APERTURE)
    with pytest.raises(ValueError, match=r"outside the motor's travel \[0.005, 0.2\]"):
        open_aperture(mid, {"ExitSlit.totalHeight": 0.5})
