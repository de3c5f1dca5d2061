"""The torch engine against RAYX: ray for ray, in distribution, and its gradients.

RAYX (the pip wheel) is the reference throughout; nothing here mocks it.  Ray for ray, the
torch engine is fed RAYX's own emitted source rays and RAYX's random counters (the slits'
Fraunhofer kicks are random), with slope errors off in both engines; in distribution it
draws its own rays with slope errors on.
"""

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import rayx
import torch

from bluesky_offsets.physics import effects
from bluesky_offsets.physics.engine import (FEATURES, TorchEngine, TorchOptions, compile_beamline, device_agreement,
                                           rays_from_arrays, sample_source, trace_rays)
from bluesky_offsets.physics.engine import random_streams as rnd
from bluesky_offsets.physics.metrixs import build_beamline
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.rml import read_rml
from bluesky_offsets.physics.twin import HistogramSpec, RayxEngine, Twin, TraceRequest, footprint
from bluesky_offsets.physics.rayx_calls import fix_seed

SHARED = Path(__file__).resolve().parent / "data" / "reference"  # provenance: its README.md
RAYUI_FILES = sorted((SHARED / "rayui-misalignment").glob("*.rml"))

MIRRORS = ("M1-Cylinder", "Plane Mirror", "Spherical Grating", "E1", "E2")
NO_SLOPE = {m: {"slopeErrorSag": 0.0, "slopeErrorMer": 0.0} for m in MIRRORS}
APERTURES = {"ASBL": ("openingWidth", "openingHeight"), "Entrance-Slit": ("openingWidth", "openingHeight"),
             "Exit Slit": ("openingWidth", "openingHeight")}
N_RAYS = 2000


def _merge(*overrides):
    out = {}
    for ov in overrides:
        for obj, fields in (ov or {}).items():
            out.setdefault(obj, {}).update(fields)
    return out


def _rayx_events(bl, n_rays, seed, tmp_path):
    """RAYX's events, sorted by path and event, from a trace of ``bl`` after fixSeed(seed)."""
    path = bl.write(tmp_path / "t.rml")
    rb = rayx.import_beamline(str(path))
    rb.sources[0].numberOfRays = n_rays
    fix_seed(seed)
    rays = rb.trace()
    n_objects = len(rb.sources) + len(rb.elements)
    pid, peid = np.asarray(rays.path_id), np.asarray(rays.path_event_id)
    order = np.lexsort((peid, pid))
    col = {k: np.asarray(getattr(rays, k))[order] for k in
           ("path_id", "object_id", "position_x", "position_y", "position_z",
            "direction_x", "direction_y", "direction_z", "energy")}
    return rays, col, n_objects


def _ray_for_ray(values, overrides, seed, tmp_path):
    """Trace with RAYX, feed its emitted rays to the torch engine, compare every hit."""
    ov = _merge(NO_SLOPE, overrides)
    bl = build_beamline(values, overrides=ov, n_rays=N_RAYS)
    rays, ev, n_objects = _rayx_events(bl, N_RAYS, seed, tmp_path)
    _, _, good = footprint(rays, n_objects, N_RAYS)
    src = ev["object_id"] == 0
    pos = np.column_stack([ev["position_x"], ev["position_y"], ev["position_z"]])
    dirs = np.column_stack([ev["direction_x"], ev["direction_y"], ev["direction_z"]])
    # RAYX's counters after its 14 source draws: the slits' kicks come from the same stream
    ctr = rnd.rayx_counters(N_RAYS, rnd.rayx_trace_seed(seed)) + 14
    given = rays_from_arrays(pos[src], dirs[src], ev["energy"][src], counters=ctr)
    cb = compile_beamline(values, ov)
    beam = trace_rays(cb, given, keep_hits=True)
    alive = beam.alive[0].numpy()
    near_edge = _near_an_edge(cb, beam)
    mismatch = np.setxor1d(np.nonzero(alive)[0], good)
    assert not np.setdiff1d(mismatch, np.nonzero(near_edge)[0]).size, \
        f"surviving rays differ: {mismatch[:10]} (RAYX {len(good)}, torch {int(alive.sum())})"
    common = np.intersect1d(np.nonzero(alive)[0], good)
    worst = 0.0
    for k, name in enumerate(cb.names, start=1):
        sel = ev["object_id"] == k
        last = {}
        for p, q in zip(ev["path_id"][sel], pos[sel]):
            last[p] = q  # the image plane: the path's last crossing
        ref = np.array([last[p] for p in common]).reshape(-1, 3)
        ours = beam.hits[name][0].numpy()[common]
        if len(common):
            worst = max(worst, float(np.abs(ref - ours).max()))
    assert worst <= 1e-6, f"largest hit-point difference {worst:.3g} mm"
    return len(good), worst


def _near_an_edge(cb, beam, tol=1e-9):
    """Rays whose hit on an outline or opening lies within ``tol`` mm of its edge."""
    near = np.zeros(beam.alive.shape[1], bool)
    for opt in cb.optics:
        h = beam.hits[opt.name][0].numpy()
        edges = []
        if opt.cutout is not None:
            edges += [(0, opt.cutout[1]), (2, opt.cutout[2])]
        if opt.opening is not None:
            edges += [(0, opt.opening[1]), (2, opt.opening[2])]
        for axis, width in edges:
            w = float(width if not torch.is_tensor(width) else width.flatten()[0])
            near |= np.abs(np.abs(h[:, axis]) - w / 2) < tol
    return near


# --------------------------------------------------------------------------- #
# ray for ray
# --------------------------------------------------------------------------- #
def test_source_rays_are_rayxs_own_for_the_same_seed(tmp_path):
    """sampling='rayx' draws RAYX's counter-based stream: the emitted rays agree to the last bits."""
    bl = build_beamline(METRIXS.reference, n_rays=N_RAYS)
    _, ev, _ = _rayx_events(bl, N_RAYS, 11, tmp_path)
    src = ev["object_id"] == 0
    cb = compile_beamline(METRIXS.reference)
    rays, _ = sample_source(cb, N_RAYS, 11, sampling="rayx")
    for ours, key in ((rays.x, "position_x"), (rays.y, "position_y"), (rays.z, "position_z"),
                      (rays.dx, "direction_x"), (rays.dy, "direction_y"), (rays.dz, "direction_z")):
        np.testing.assert_allclose(ours[0].numpy(), ev[key][src], rtol=0, atol=1e-15)


def test_nominal_ray_for_ray(tmp_path):
    n_good, worst = _ray_for_ray(METRIXS.reference, None, 3, tmp_path)
    assert n_good > 0.7 * N_RAYS  # the nominal focus: transmission ~0.79


@pytest.mark.parametrize("name", METRIXS.names)
def test_each_parameter_at_both_box_edges_ray_for_ray(name, tmp_path):
    j = METRIXS.index(name)
    for edge in (METRIXS.low[j], METRIXS.high[j]):
        values = METRIXS.reference.copy()
        values[j] = edge
        _ray_for_ray(values, None, 5 + j, tmp_path)


def test_random_box_draws_ray_for_ray(tmp_path):
    """20 draws from the whole box that light the screen (a dark draw proves nothing; about
    one whole-box draw in 45 puts 10 of 2000 rays on the screen)."""
    rng = np.random.default_rng(20261124)
    draws = METRIXS.sample_uniform(1536, rng)
    screen = TorchEngine().trace_many([TraceRequest(v, {}, 1) for v in draws], N_RAYS)
    lit = [v for v, r in zip(draws, screen) if r.n_hits >= 10]
    assert len(lit) >= 20
    for i, values in enumerate(lit[:20]):
        n_good, _ = _ray_for_ray(values, None, 100 + i, tmp_path)
        assert n_good > 0


@pytest.mark.parametrize("openings", [{"ASBL.totalWidth": 4.0, "ASBL.totalHeight": 2.0},
                                      {"ExitSlit.totalHeight": 0.1}, {"ExitSlit.totalHeight": 0.2},
                                      {"ASBL.totalWidth": 0.2, "ExitSlit.totalHeight": 0.005}])
def test_open_and_narrow_slits_ray_for_ray(openings, tmp_path):
    _ray_for_ray(METRIXS.from_mapping(openings), None, 21, tmp_path)


TWIN_EFFECTS = [("chamber_x", {"x": 0.6}), ("chamber_y", {"y": -0.5}), ("chamber_z", {"z": -25.0}),
                ("chamber_rotation", {"angle": 60.0}), ("source_size", {"size": 3.0}),
                ("source_divergence", {"divergence": -0.45}), ("photon_energy", {"delta": 0.02}),
                ("thermal_bump_m1", {"height": 400.0}), ("grating_line_density", {"delta": -0.1})]


@pytest.mark.parametrize("name, values", TWIN_EFFECTS, ids=[e for e, _ in TWIN_EFFECTS])
def test_each_twin_effect_ray_for_ray(name, values, tmp_path):
    """Every twin-level effect of the library, at a magnitude that visibly changes the footprint
    (the source size needs 4x its model value: at the nominal focus +100 % widens it by 1-3 %)."""
    ov = effects.twin_overrides({name: values})
    twin = Twin("torch", scheduler="inline", n_rays=4000)
    base = twin.trace(METRIXS.reference, seed=2, keep_rays=True).summary()
    moved = twin.trace(METRIXS.reference, overrides=ov, seed=2, keep_rays=True).summary()
    changes = [abs(moved["transmission"] - base["transmission"]) / 0.01,
               *(abs(moved[k] - base[k]) / 0.01 for k in ("centroid_x", "centroid_y")),
               *(abs(moved[k] / base[k] - 1) / 0.03 for k in ("width_x", "width_y"))]
    assert max(changes) > 1, f"{name} hardly changes the footprint: {base} -> {moved}"
    _ray_for_ray(METRIXS.reference, ov, 31, tmp_path)


@pytest.mark.parametrize("path", RAYUI_FILES, ids=lambda p: p.stem)
def test_rayui_reference_files_reproduced(path, tmp_path):
    """RAY-UI's misaligned outputs (plane mirror, plane grating with azimuth errors,
    ellipsoids), traced by the torch engine from the file's own Matrix-source rays."""
    beamline = read_rml(path)
    n_rays = int(beamline.objects[0].get_float("numberRays"))
    rays, ev, n_objects = _rayx_events(beamline, n_rays, 0, tmp_path)
    src = ev["object_id"] == 0
    pos = np.column_stack([ev["position_x"], ev["position_y"], ev["position_z"]])[src]
    dirs = np.column_stack([ev["direction_x"], ev["direction_y"], ev["direction_z"]])[src]
    cb = compile_beamline(np.zeros((1, 0)), beamline=beamline)
    beam = trace_rays(cb, rays_from_arrays(pos, dirs, ev["energy"][src]))
    csv = pd.read_csv(path.with_suffix(".csv"), sep="\t", skiprows=1).sort_values("ImagePlane_RN")
    alive = beam.alive[0].numpy()
    np.testing.assert_array_equal(np.nonzero(alive)[0], csv["ImagePlane_RN"].to_numpy())
    np.testing.assert_allclose(beam.x[0].numpy()[alive], csv["ImagePlane_OX"].to_numpy(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(beam.y[0].numpy()[alive], csv["ImagePlane_OY"].to_numpy(), rtol=0, atol=1e-6)


def test_source_misalignment_moves_the_beam_the_physical_way(tmp_path):
    """+0.2 mm source shift in x: the rays at the aperture move +0.2 mm in both engines (RAYX
    inverts a source's world frame; the RML the project writes undoes that)."""
    shifted = METRIXS.from_mapping({"U41_318eV.translationXerror": 0.2})
    means = {}
    for label, values in (("nominal", METRIXS.reference), ("shifted", shifted)):
        _, ev, _ = _rayx_events(build_beamline(values, n_rays=N_RAYS), N_RAYS, 4, tmp_path)
        at_asbl = ev["object_id"] == 1  # absorbed rays included: the slit's edges do not bias it
        cb = compile_beamline(values)
        rays, draws = sample_source(cb, N_RAYS, 4)
        beam = trace_rays(cb, rays, draws, keep_hits=True)
        means[label] = (ev["position_x"][at_asbl].mean(), beam.hits["ASBL"][0, :, 0].mean().item())
    for k in range(2):
        assert means["shifted"][k] - means["nominal"][k] == pytest.approx(0.2, abs=0.02)


# --------------------------------------------------------------------------- #
# in distribution
# --------------------------------------------------------------------------- #
def _bright_configurations(n, rng):
    """Random configurations within ±5 % of the box around its centre that light the screen,
    E1/E2 rolls at the real-beamline box; found with the torch engine."""
    centre = 0.5 * (METRIXS.low + METRIXS.high)
    found = [METRIXS.reference]
    eng = TorchEngine()
    while len(found) < n + 1:
        cand = centre + rng.uniform(-0.05, 0.05, (64, 34)) * METRIXS.span
        res = eng.trace_many([TraceRequest(v, {}, 3) for v in cand], 500)
        found += [v for v, r in zip(cand, res) if r.transmission > 0.05]
    return np.array(found[:n + 1])


def test_histograms_agree_with_rayx_in_distribution():
    """Own source sampling, slope errors on: over 50 random bright configurations and the
    nominal one, RAYX's and the torch engine's histograms agree within counting noise."""
    rng = np.random.default_rng(7)
    configs = _bright_configurations(50, rng)
    n = 4000
    ours = TorchEngine().trace_many([TraceRequest(v, {}, 1000 + i) for i, v in enumerate(configs)], n,
                                    keep_rays=True)
    ref = Twin(scheduler="inline").trace_batch(configs, n_rays=n, seed=5000, keep_rays=True, progress=False)
    chi2 = dof = 0.0
    for a, b in zip(ours, ref.results):
        for k in range(2):
            pooled = np.concatenate([a.rays[:, k], b.rays[:, k]])
            # 12 equal-probability bins per axis, plus the rays that did not arrive
            edges = np.unique(np.quantile(pooled, np.linspace(0, 1, 13)))
            ca = np.append(np.histogram(a.rays[:, k], edges)[0], n - a.n_hits)
            cb = np.append(np.histogram(b.rays[:, k], edges)[0], n - b.n_hits)
            used = ca + cb > 0
            chi2 += (((ca - cb) ** 2)[used] / (ca + cb)[used]).sum()
            dof += used.sum() - 1
    ratio = chi2 / dof
    assert abs(ratio - 1) < 4 * math.sqrt(2 / dof), f"chi2/dof {ratio:.3f} over {dof:.0f} dof"


def test_the_slit_kicks_drawn_in_blocks_are_those_drawn_one_try_at_a_time():
    """RAYX's rejection sampler of a slit's kick, written as RAYX loops (one try per ray at a
    time), gives the accepted draws and the counters after them that the blocked sampler gives:
    slits of microns to millimetres, closed ones (no draws) among them, batches of any shape."""
    def one_at_a_time(ctr, dim, wl):
        u, ctr = torch.full(ctr.shape, 0.5, dtype=torch.float64), ctr.clone()
        for i in np.flatnonzero(dim.numpy() != 0):
            while True:
                u1, u2 = rnd.squares_uniform(ctr[i:i + 1]), rnd.squares_uniform(ctr[i:i + 1] + 1)
                ctr[i] += 2
                b = float(dim[i]) * 1e6
                v = math.pi * b * torch.sin((u1 - 0.5) * (10.0 * wl / b)) / wl
                if float((torch.sin(v) / v) ** 2 if float(v) != 0 else 1.0) >= float(u2):  # RAYX's test
                    u[i] = u1[0]
                    break
        return u, ctr

    rng = np.random.default_rng(5)
    for n, wl in ((300, 2.0), (200, 0.5)):
        ctr = rnd.rayx_counters(n, rng.uniform())
        dim = torch.as_tensor(10.0 ** rng.uniform(-3, 0.5, n)) * torch.as_tensor(rng.uniform(size=n) > 0.1)
        want = one_at_a_time(ctr, dim, wl)
        got = rnd.fraunhofer_uniform_rayx(ctr.reshape(4, -1), dim.reshape(4, -1), wl)
        assert torch.equal(got[0].reshape(-1), want[0]) and torch.equal(got[1].reshape(-1), want[1])


@pytest.mark.parametrize("sampling", ["fast", "rayx"])
def test_compacting_trace_is_the_dense_trace_bit_for_bit(sampling):
    """Dropping the rays an element stopped (``compact``) changes no surviving ray: whole-box
    draws (most rays stop at the exit slit), bright ones, slope errors on, the chamber moved."""
    rng = np.random.default_rng(31)
    values = np.concatenate([METRIXS.sample_uniform(200, rng), _bright_configurations(6, rng)])
    chamber = {"ImagePlane": {"translationXerror": torch.as_tensor(rng.uniform(-1, 1, len(values))),
                              "translationZerror": torch.as_tensor(rng.uniform(-30, 30, len(values)))}}
    bl = compile_beamline(values, chamber)
    rays, draws = sample_source(bl, 300, 9, sampling=sampling)
    with torch.no_grad():
        dense = trace_rays(bl, rays, draws)
        compact = trace_rays(bl, rays, draws, compact=True)
    alive = dense.alive
    assert 0 < alive.sum() < alive.numel() // 20
    assert torch.equal(compact.alive, alive)
    assert torch.equal(compact.x[alive], dense.x[alive]) and torch.equal(compact.y[alive], dense.y[alive])
    with pytest.raises(ValueError, match="hard beam"):
        trace_rays(bl, rays, draws, edge=0.01, compact=True)


def test_trace_batch_agrees_with_rayx_in_distribution():
    """The dataset's batch trace (each configuration its own rays from one stream, kicks and
    slope errors drawn as rays arrive, compacted): RAYX's histograms within counting noise."""
    configs = _bright_configurations(30, np.random.default_rng(8))
    n = 4000
    spec = HistogramSpec(400, (-10.0, 10.0), 600, (-3.0, 3.0))  # 50 x 10 µm bins: the focus spans many
    ours = TorchEngine(hist=spec).trace_batch(configs, n_rays=n, seed=77)
    again = TorchEngine(hist=spec).trace_batch(configs, n_rays=n, seed=77)
    np.testing.assert_array_equal(ours.hist_x, again.hist_x)
    ref = Twin(RayxEngine(hist=spec), scheduler="inline").trace_batch(configs, n_rays=n, seed=9000, progress=False)
    chi2 = dof = 0.0
    for a, b in ((ours.hist_x, ref.hist_x), (ours.hist_y, ref.hist_y)):
        # the bins, plus the rays that did not arrive (multinomial: one constraint per configuration)
        ca = np.column_stack([np.rint(a * n), n - ours.n_hits])
        cb = np.column_stack([np.rint(b * n), n - ref.n_hits])
        used = ca + cb > 0
        chi2 += (((ca - cb) ** 2)[used] / (ca + cb)[used]).sum()
        dof += used.sum() - len(ca)
    ratio = chi2 / dof
    assert abs(ratio - 1) < 4 * math.sqrt(2 / dof), f"chi2/dof {ratio:.3f} over {dof:.0f} dof"


# --------------------------------------------------------------------------- #
# gradients
# --------------------------------------------------------------------------- #
GRAD_EFFECTS = {"chamber_x": {"x": 0.1}, "chamber_y": {"y": -0.1}, "chamber_z": {"z": 8.0},
                "chamber_rotation": {"angle": 20.0}, "source_size": {"size": 0.2},
                "source_divergence": {"divergence": 0.15}, "photon_energy": {"delta": 0.005},
                "grating_line_density": {"delta": 0.05}, "thermal_bump_m1": {"height": 200.0}}
EFFECT_SCALE = {"chamber_z": 10.0, "chamber_rotation": 10.0, "thermal_bump_m1": 100.0,
                "photon_energy": 0.01, "grating_line_density": 0.1}


def test_feature_jacobian_equals_finite_differences_of_the_same_engine():
    """Autograd Jacobians of the soft features match central differences at fixed rays to
    1 % for all 34 parameters and every continuous twin-level effect parameter."""
    eng = TorchEngine()
    rng = np.random.default_rng(3)
    values = np.stack([METRIXS.reference + 0.01 * METRIXS.span * rng.uniform(-1, 1, 34) for _ in range(2)])
    values[:, [METRIXS.index("E1.rotationZerror"), METRIXS.index("E2.rotationZerror")]] = 0.0
    n = 3000
    feats, jac, names = eng.jacobian("features", values, GRAD_EFFECTS, n_rays=n, seed=9)
    assert jac.shape == (2, len(FEATURES), 34 + len(GRAD_EFFECTS)) and torch.isfinite(jac).all()

    def at(vals, effs):
        with torch.no_grad():
            return eng.products("features", vals, effs, n_rays=n, seed=9)

    scale = jac.abs().amax(dim=2, keepdim=True)  # entries above noise: relative to the row's largest
    for j, name in enumerate(names):
        if j < 34:
            h = 1e-6 * METRIXS.span[j]
            up, down = values.copy(), values.copy()
            up[:, j] += h
            down[:, j] -= h
            fd = (at(up, GRAD_EFFECTS) - at(down, GRAD_EFFECTS)) / (2 * h)
        else:
            eff, par = name.split(".")
            h = 1e-6 * EFFECT_SCALE.get(eff, 1.0)
            up = {k: dict(v) for k, v in GRAD_EFFECTS.items()}
            down = {k: dict(v) for k, v in GRAD_EFFECTS.items()}
            up[eff][par] += h
            down[eff][par] -= h
            fd = (at(values, up) - at(values, down)) / (2 * h)
        ad = jac[:, :, j]
        big = ad.abs() > 1e-3 * scale[:, :, 0]
        rel = ((fd - ad).abs() / ad.abs())[big]
        assert rel.numel() == 0 or rel.max() < 0.01, f"{name}: autograd vs finite differences {rel.max():.3g}"


def test_forward_and_reverse_mode_agree_and_histogram_jacobian():
    eng = TorchEngine()
    values = METRIXS.reference
    f_r, j_r, _ = eng.jacobian("features", values, {"chamber_z": {"z": 3.0}}, n_rays=500, seed=2, mode="reverse")
    f_f, j_f, _ = eng.jacobian("features", values, {"chamber_z": {"z": 3.0}}, n_rays=500, seed=2, mode="forward")
    torch.testing.assert_close(f_r, f_f)
    torch.testing.assert_close(j_r, j_f, rtol=1e-9, atol=1e-12)
    h, jh, names = eng.jacobian("histograms", values, {"chamber_z": {"z": 3.0}}, n_rays=1500, seed=2)
    assert h.shape == (1, 100) and jh.shape == (1, 100, 35)
    # moving E2's pitch moves the vertical histogram: its Jacobian column is not zero there
    assert jh[0, 50:, METRIXS.index("E2.rotationXerror")].abs().sum() > 0


# --------------------------------------------------------------------------- #
# the engine as a twin
# --------------------------------------------------------------------------- #
def test_torch_twin_batches_are_reproducible_and_match_single_traces():
    twin = Twin("torch", n_rays=3000)
    rng = np.random.default_rng(1)
    values = METRIXS.reference + 0.005 * METRIXS.span * rng.uniform(-1, 1, (5, 34))
    values[:, [METRIXS.index("E1.rotationZerror"), METRIXS.index("E2.rotationZerror")]] = 0.0
    a = twin.trace_batch(values, seed=4, progress=False)
    b = twin.trace_batch(values, seed=4, progress=False)
    np.testing.assert_array_equal(a.hist_x, b.hist_x)
    one = twin.trace(values[2], seed=6)  # row 2 of seed 4 is seed 6
    np.testing.assert_array_equal(one.hist_y, a[2].hist_y)
    assert twin._client is None  # batched in this process, no Dask cluster started


def test_float32_is_close_to_float64():
    f64 = TorchEngine().trace(TraceRequest(METRIXS.reference, {}, 1), 5000, keep_rays=True)
    f32 = TorchEngine(options={"dtype": "float32"}).trace(TraceRequest(METRIXS.reference, {}, 1), 5000,
                                                          keep_rays=True)
    assert abs(f32.n_hits - f64.n_hits) <= 5
    assert np.abs(f32.rays.mean(0) - f64.rays.mean(0)).max() < 1e-3


def test_options_refuse_unknown_keys_and_bad_values():
    with pytest.raises(ValueError, match="unknown torch engine option"):
        TorchOptions.from_mapping({"dtyp": "float32"})
    with pytest.raises(ValueError, match="sampling"):
        TorchOptions(sampling="mt")
    with pytest.raises(ValueError, match="unknown engine"):
        Twin("rayy")


def test_simulate_compares_both_engines(capsys):
    import json

    from bluesky_offsets.commands.cli import main
    assert main(["simulate", "--engine", "both", "--rays", "4000", "--seed", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["engine"].split()[0] for r in out["runs"]] == ["rayx", "torch"]
    t = [r["transmission"] for r in out["runs"]]
    assert abs(t[0] - t[1]) < 5 * math.sqrt(2 * 0.79 * 0.21 / 4000)
    assert out["comparison"]["chi2_per_dof"] < 1 + 5 * out["comparison"]["sigma"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")
def test_cuda_traces_the_same_rays_as_the_cpu():
    r = device_agreement("cuda")
    assert r["same_survivors"] and r["survivors"] > 0
    assert r["max_dx_mm"] < 1e-9 and r["max_dy_mm"] < 1e-9


def test_a_batch_traced_in_chunks_gives_what_one_piece_gives():
    """max_batch splits a batch's rays into chunks; the histograms, soft products and their
    Jacobians are those of the whole (the chunks' fractions once summed as if each were all: a
    calibrate's fresh-ray check read 5x the light at 59 frames of 40,000 rays)."""
    from sim_iocs.truth import default_start
    v = np.tile(default_start(), (3, 1))
    v[1, METRIXS.index("E1.rotationXerror")] += 0.05
    reqs = [TraceRequest(row, {}, seed=k) for k, row in enumerate(v)]
    whole, chunked = TorchEngine(), TorchEngine(options={"max_batch": 3 * 700})
    for a, b in zip(whole.trace_many(reqs, 3000), chunked.trace_many(reqs, 3000)):
        np.testing.assert_allclose(b.hist_x, a.hist_x, atol=1e-12)
        assert b.n_hits == a.n_hits
    for what in ("histograms", "features"):
        pa = whole.products(what, v, n_rays=3000, seed=1)
        pb = chunked.products(what, v, n_rays=3000, seed=1)
        torch.testing.assert_close(pb, pa, rtol=1e-9, atol=1e-12)
        ja = whole.jacobian(what, v, n_rays=3000, seed=1)[1]
        jb = chunked.jacobian(what, v, n_rays=3000, seed=1)[1]
        torch.testing.assert_close(jb, ja, rtol=1e-7, atol=1e-10)
