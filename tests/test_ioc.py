"""The simulated METRIXS IOC, from the outside: motor records, focus chamber, robustness.

All against the real caproto IOC in a subprocess on 127.0.0.1 (fixtures in
conftest.py), with caproto's client and command-line tools.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec
from sim_iocs.motor_record import trapezoid
from sim_iocs.truth import Truth, default_start

HIST = HistogramSpec()


# --------------------------------------------------------------------------- #
# pure parts
# --------------------------------------------------------------------------- #
def test_trapezoid_profile_reaches_target_in_expected_time():
    duration, s = trapezoid(2.0, 1.0, 0.5)  # 0.25 accel + 1.5 cruise + 0.25 decel distance
    assert duration == pytest.approx(2.5)
    assert s(0) == 0 and s(duration) == pytest.approx(2.0) and s(10) == pytest.approx(2.0)
    assert s(0.5) == pytest.approx(0.25) and s(1.25) == pytest.approx(1.0)
    ts = np.linspace(0, duration, 101)
    assert np.all(np.diff([s(t) for t in ts]) >= -1e-12)
    d_short, s_short = trapezoid(-0.1, 1.0, 0.5)  # never reaches cruise speed
    assert d_short == pytest.approx(2 * np.sqrt(0.1 / 2.0)) and s_short(d_short) == pytest.approx(-0.1)
    assert trapezoid(0.0, 1.0, 0.2)[0] == 0.0


def test_truth_from_seed_file_and_errors(tmp_path):
    t = Truth.from_seed(3)
    assert np.all(np.abs(t.offsets) <= 0.2) and np.any(t.offsets != 0)
    again = Truth.from_seed(3)
    np.testing.assert_array_equal(again.offsets, t.offsets)
    # salted: the same seed gives another id, so no seed is found by hashing seeds; the
    # truth written out (salt included) keeps its id
    assert t.truth_id != again.truth_id and Truth.from_mapping(t.to_dict()).truth_id == t.truth_id
    start = default_start()
    assert np.all((start >= METRIXS.low) | ~METRIXS.motorized) and np.all((start <= METRIXS.high) | ~METRIXS.motorized)
    np.testing.assert_allclose(t.true_values(start), np.where(METRIXS.motorized, start, METRIXS.reference)
                               + t.offsets * METRIXS.span)
    f = tmp_path / "t.json"
    f.write_text(json.dumps({"offsets": {"E1.rotationXerror": 0.1},
                             "offsets_physical": {"M1_Cylinder.radius": 0.03},
                             "overrides": {"ImagePlane": {"translationZerror": 2}}}))
    t2 = Truth.from_file(f)
    assert t2.offsets[METRIXS.index("E1.rotationXerror")] == 0.1
    assert t2.physical_offsets[METRIXS.index("M1_Cylinder.radius")] == pytest.approx(0.03)
    assert t2.overrides == {"ImagePlane": {"translationZerror": 2.0}}
    with pytest.raises(ValueError, match="limited to"):
        Truth.from_mapping({"offsets": {"E1.rotationXerror": 0.3}})
    with pytest.raises(ValueError, match="unknown parameter 'E1.pitch'"):
        Truth.from_mapping({"offsets": {"E1.pitch": 0.1}})
    with pytest.raises(ValueError, match="unknown keys"):
        Truth.from_mapping({"offset": {}})
    with pytest.raises(ValueError, match="not a motor"):
        Truth.from_mapping({"start": {"E1.longHalfAxisA": 20700}})
    with pytest.raises(ValueError, match="outside the motor limits"):
        Truth.from_mapping({"start": {"E1.rotationZerror": 0.0}})
    # a thermal bump turns M1 into a toroid: RML fields may be words as well as numbers
    bump = Truth.from_mapping({"overrides": {"M1-Cylinder": {"type": "Toroid", "longRadius": "-1.4e6"}}})
    assert bump.overrides == {"M1-Cylinder": {"type": "Toroid", "longRadius": -1.4e6}}
    with pytest.raises(ValueError, match="neither a number nor a word"):
        Truth.from_mapping({"overrides": {"M1-Cylinder": {"longRadius": [1]}}})


def test_bad_truth_file_gives_clear_error_and_exit_2(tmp_path):
    f = tmp_path / "bad.json"
    f.write_text("{not json")
    r = subprocess.run([sys.executable, "-m", "sim_iocs.metrixs", "--prefix", "BAD:", "--truth", str(f)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "not valid JSON" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "bluesky_offsets.commands.cli", "ioc", "--truth", str(tmp_path / "none.json")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "does not exist" in r.stderr


# --------------------------------------------------------------------------- #
# PVs and the command-line tools
# --------------------------------------------------------------------------- #
def test_list_pvs_lists_28_motor_records_and_detector(metrixs_ioc):
    log = metrixs_ioc.log()
    P = metrixs_ioc.prefix
    motors = [line.split()[0] for line in log.splitlines() if line.startswith(f"  {P}") and "chamber:" not in line]
    assert len(motors) == 28
    assert motors == [P + p.device.replace(".", ":") for p in METRIXS if p.motorized]
    for pv in ("Acquire", "NumRays", "AcquireTime", "HistX", "HistY", "Image", "TotalCounts", "AxisX", "AxisY",
               "Status", "Message", "TruthId"):
        assert f"{P}chamber:{pv} " in log
    assert "radius" not in "".join(motors) and "HalfAxis" not in log  # fixed parameters are no motors


def test_caproto_cli_reads_and_moves_a_motor(metrixs_ioc, ca_tools):
    P, env = metrixs_ioc.prefix, metrixs_ioc.env
    rec = P + "asbl:tx"

    # caproto-get prints a failed read (its 1 s default timeout, on a loaded machine) to stdout and exits 0
    def get(*pvs):
        r = subprocess.run([ca_tools["caproto-get"], "--no-repeater", "-w", "10", "-t", *pvs], env=env,
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        values = r.stdout.splitlines()
        assert len(values) == len(pvs), r.stdout
        return values

    rbv, hlm, llm, egu = get(rec + ".RBV", rec + ".HLM", rec + ".LLM", rec + ".EGU")
    assert (float(hlm), float(llm), egu) == (0.2, -0.2, "mm")
    target = round(float(rbv) + 0.05, 6)
    r = subprocess.run([ca_tools["caproto-put"], "--no-repeater", "-c", "-w", "10", rec, str(target)], env=env,
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    new_rbv, dmov, val, desc = get(rec + ".RBV", rec + ".DMOV", rec + ".VAL", rec + ".DESC")
    assert abs(float(new_rbv) - target) <= 1e-6 and dmov == "1" and float(val) == pytest.approx(target)
    assert desc == "ASBL.translationXerror"


def test_put_completion_waits_for_done_moving(metrixs_ioc, ca):
    rec = metrixs_ioc.prefix + "source:tx"
    velo = ca.get(rec + ".VELO")
    mres = ca.get(rec + ".MRES")
    dmov_seen = []
    sub = ca.pv(rec + ".DMOV").subscribe()

    def on_dmov(sub, resp):
        dmov_seen.append(int(resp.data[0]))

    sub.add_callback(on_dmov)  # caproto holds callbacks weakly: keep a name for it
    try:
        ca.put(rec + ".VELO", 0.25)
        start = ca.get(rec + ".RBV")
        target = start + (0.2 if start < 0 else -0.2)
        t0 = time.monotonic()
        ca.put(rec, target, wait=True)
        elapsed = time.monotonic() - t0
        assert elapsed >= 0.2 / 0.25 * 0.9  # the put completed only after the motion
        assert ca.get(rec + ".DMOV") == 1 and abs(ca.get(rec + ".RBV") - target) <= mres
        assert ca.get(rec + ".DRBV") == pytest.approx(ca.get(rec + ".RBV"))
        # the monitor of the move's last DMOV (1) can arrive after the put has completed (seen on a
        # fresh clone's CI: [1, 0] where [0, 1] was asked, the 1 being this move's): wait for it
        deadline = time.monotonic() + 5.0
        while not (dmov_seen and dmov_seen[-1] == 1) and time.monotonic() < deadline:
            time.sleep(0.01)
        n = len(dmov_seen)
        ca.put(rec, target, wait=True)  # zero-length move: DMOV still pulses
        time.sleep(0.2)
        assert dmov_seen[n:][:2] == [0, 1]
        assert 0 in dmov_seen and dmov_seen[-1] == 1
    finally:
        sub.clear()
        ca.put(rec + ".VELO", velo)
        ca.put(rec, 0.0)


def test_limit_violation_refused_with_lvio_and_no_motion(metrixs_ioc, ca):
    rec = metrixs_ioc.prefix + "asbl:ty"
    before = ca.get(rec + ".RBV")
    ca.put(rec, 0.5, wait=True)  # HLM is 0.2
    assert ca.get(rec + ".LVIO") == 1
    assert ca.get(rec + ".RBV") == before and ca.get(rec + ".VAL") == before and ca.get(rec + ".DMOV") == 1
    ca.put(rec + ".DVAL", -0.3, wait=True)
    assert ca.get(rec + ".LVIO") == 1 and ca.get(rec + ".RBV") == before
    ca.put(rec, before + 0.01, wait=True)
    assert ca.get(rec + ".LVIO") == 0 and ca.get(rec + ".RBV") == pytest.approx(before + 0.01, abs=1e-6)
    ca.put(rec, before, wait=True)
    # soft limits opened beyond the travel: the axis stops at its limit switch (0.1 mm past the box)
    try:
        ca.put(rec + ".HLM", 10.0)
        assert ca.get(rec + ".DHLM") == 10.0
        ca.put(rec, 0.5, wait=True)
        assert ca.get(rec + ".HLS") == 1 and ca.get(rec + ".RBV") == pytest.approx(0.3, abs=1e-5)
        assert ca.get(rec + ".VAL") == pytest.approx(ca.get(rec + ".RBV")) and ca.get(rec + ".MSTA") & (1 << 2)
    finally:
        ca.put(rec + ".HLM", 0.2)
        ca.put(rec, before, wait=True)
    assert ca.get(rec + ".HLS") == 0


def test_stop_halts_motion_and_completes_pending_put(metrixs_ioc, ca):
    rec = metrixs_ioc.prefix + "source:ty"
    velo = ca.get(rec + ".VELO")
    try:
        ca.put(rec + ".VELO", 0.1)
        done = threading.Event()
        threading.Thread(target=lambda: (ca.put(rec, 0.2, wait=True, timeout=30), done.set()), daemon=True).start()
        time.sleep(0.6)
        assert ca.get(rec + ".DMOV") == 0 and ca.get(rec + ".MOVN") == 1
        ca.put(rec + ".STOP", 1)
        assert done.wait(5), "the pending put-completion must finish when the motor is stopped"
        rbv = ca.get(rec + ".RBV")
        assert 0.0 < rbv < 0.15 and ca.get(rec + ".DMOV") == 1
        assert ca.get(rec + ".VAL") == pytest.approx(rbv)  # the record sets VAL to where it stopped
        time.sleep(0.3)
        assert ca.get(rec + ".RBV") == rbv
        # SPMG Pause holds the move (DMOV stays 0), Go finishes it
        done.clear()
        threading.Thread(target=lambda: (ca.put(rec, 0.0, wait=True, timeout=30), done.set()), daemon=True).start()
        time.sleep(0.3)
        ca.put(rec + ".SPMG", "Pause")
        held = ca.get(rec + ".RBV")
        time.sleep(0.3)
        assert ca.get(rec + ".RBV") == held and ca.get(rec + ".DMOV") == 0 and not done.is_set()
        ca.put(rec + ".SPMG", "Go")
        assert done.wait(10) and ca.get(rec + ".RBV") == pytest.approx(0.0, abs=1e-6)
        # home: back to the start position, at-home and homed flags
        ca.put(rec, 0.05, wait=True)
        ca.put(rec + ".HOMR", 1)
        assert ca.get(rec + ".RBV") == pytest.approx(0.0, abs=1e-6) and ca.get(rec + ".ATHM") == 1
        assert ca.get(rec + ".MSTA") & (1 << 14)
    finally:
        ca.put(rec + ".SPMG", "Go")
        ca.put(rec + ".VELO", velo)
        ca.put(rec, 0.0)


def test_user_dial_offset_direction_set_mode_tweak_and_relative(metrixs_ioc, ca):
    rec = metrixs_ioc.prefix + "exit_slit:rz"
    drbv0 = ca.get(rec + ".DRBV")
    try:
        ca.put(rec + ".OFF", 0.05)
        assert ca.get(rec + ".RBV") == pytest.approx(drbv0 + 0.05)
        assert ca.get(rec + ".HLM") == pytest.approx(0.35) and ca.get(rec + ".DRBV") == drbv0
        ca.put(rec + ".DIR", "Neg")
        assert ca.get(rec + ".RBV") == pytest.approx(-drbv0 + 0.05)
        assert ca.get(rec + ".HLM") == pytest.approx(0.35) and ca.get(rec + ".LLM") == pytest.approx(-0.25)
        ca.put(rec + ".DIR", "Pos")
        ca.put(rec + ".SET", "Set")
        ca.put(rec, 0.2)  # calibrate: no motion, OFF absorbs it (FOFF Variable)
        ca.put(rec + ".SET", "Use")
        assert ca.get(rec + ".RBV") == pytest.approx(0.2) and ca.get(rec + ".DRBV") == drbv0
        assert ca.get(rec + ".OFF") == pytest.approx(0.2 - drbv0)
        ca.put(rec + ".OFF", 0.0)
        ca.put(rec + ".TWV", 0.01)
        ca.put(rec + ".TWF", 1)
        assert ca.get(rec + ".RBV") == pytest.approx(drbv0 + 0.01, abs=1e-6)
        ca.put(rec + ".TWR", 1)
        ca.put(rec + ".TWR", 1)
        assert ca.get(rec + ".RBV") == pytest.approx(drbv0 - 0.01, abs=1e-6)
        ca.put(rec + ".RLV", 0.03)
        assert ca.get(rec + ".RBV") == pytest.approx(drbv0 + 0.02, abs=1e-6) and ca.get(rec + ".RLV") == 0
        msta = ca.get(rec + ".MSTA")
        assert msta & (1 << 1) and not msta & (1 << 10)  # done, not moving
    finally:
        ca.put(rec + ".SET", "Use")
        ca.put(rec + ".DIR", "Pos")
        ca.put(rec + ".OFF", 0.0)
        ca.put(rec, drbv0)


# --------------------------------------------------------------------------- #
# the focus chamber
# --------------------------------------------------------------------------- #
def _frame(ca, P):
    c = P + "chamber:"
    return {"counter": ca.get(c + "ArrayCounter"), "hx": ca.get(c + "HistX"), "hy": ca.get(c + "HistY"),
            "image": ca.get(c + "Image").reshape(HIST.bins_y, HIST.bins_x), "total": ca.get(c + "TotalCounts"),
            "n_rays": ca.get(c + "NumRays"), "status": ca.get(c + "Status", as_string=True)}


def test_acquire_gives_a_consistent_frame_and_no_truth_on_pvs(metrixs_ioc, ca):
    P = metrixs_ioc.prefix
    before = ca.get(P + "chamber:ArrayCounter")
    ca.put(P + "chamber:Acquire", 1, wait=True, timeout=60)
    f = _frame(ca, P)
    assert f["counter"] == before + 1 and f["status"] == "Idle" and ca.get(P + "chamber:Acquire") == 0
    assert f["n_rays"] == 3000 and f["total"] > 200  # the mild truth keeps the beam on the screen
    raw_x, raw_y = f["hx"] * f["n_rays"], f["hy"] * f["n_rays"]
    np.testing.assert_allclose(raw_x, np.round(raw_x), atol=1e-6)  # whole rays per bin
    assert raw_x.sum() <= f["total"] + 1e-6 and raw_y.sum() <= f["total"] + 1e-6
    assert np.all(f["image"].sum(axis=0) <= f["hx"] + 1e-12) and np.all(f["image"].sum(axis=1) <= f["hy"] + 1e-12)
    np.testing.assert_allclose(ca.get(P + "chamber:AxisX"), HIST.centers_x)
    np.testing.assert_allclose(ca.get(P + "chamber:AxisY"), HIST.centers_y)
    # the same frame at the camera's resolution: its profiles sum up to the histograms
    px, py = ca.get(P + "chamber:ProfileX"), ca.get(P + "chamber:ProfileY")
    assert px.shape == (CAMERA.bins_x,) and py.shape == (CAMERA.bins_y,)
    rx, ry = CAMERA.rebin(px, py, HIST)
    np.testing.assert_allclose(rx, f["hx"], atol=1e-12)
    np.testing.assert_allclose(ry, f["hy"], atol=1e-12)
    assert HistogramSpec.from_centers(ca.get(P + "chamber:ProfileAxisX"), ca.get(P + "chamber:ProfileAxisY")) == CAMERA
    truth = Truth.from_mapping(metrixs_ioc.truth)
    assert ca.get(P + "chamber:TruthId", as_string=True) == truth.truth_id
    # readbacks are the positions the operator set, not position + hidden offset
    assert ca.get(P + "e1:rx.RBV") == pytest.approx(0.0, abs=1e-3)


def test_acquisition_with_no_rays_gives_zeros_not_nan(metrixs_ioc, ca):
    P = metrixs_ioc.prefix
    rec = P + "m1:tx"
    pos = ca.get(rec + ".RBV")
    try:
        ca.put(rec, 1.0, wait=True)  # M1 pushed 1 mm sideways: no ray reaches the screen
        ca.put(P + "chamber:Acquire", 1, wait=True, timeout=60)
        f = _frame(ca, P)
        assert f["total"] == 0 and ca.get(P + "chamber:Transmission") == 0.0
        for k in ("hx", "hy", "image"):
            assert np.all(np.isfinite(f[k])) and not f[k].any()
    finally:
        ca.put(rec, pos, wait=True)
    ca.put(P + "chamber:NumRays", 0)
    try:  # no source rays at all: a dark frame
        ca.put(P + "chamber:Acquire", 1, wait=True, timeout=60)
        f = _frame(ca, P)
        assert f["total"] == 0 and not f["hx"].any() and np.all(np.isfinite(f["hy"]))
    finally:
        ca.put(P + "chamber:NumRays", 3000)


def test_acquisition_abort_completes_the_put(metrixs_ioc, ca):
    P = metrixs_ioc.prefix + "chamber:"
    ca.put(P + "AcquireTime", 3.0)
    try:
        done, outcome = threading.Event(), {}

        def acquire():
            outcome["status"] = ca.put(P + "Acquire", 1, wait=True, timeout=30).status
            done.set()
        threading.Thread(target=acquire, daemon=True).start()
        time.sleep(0.8)
        assert ca.get(P + "Status", as_string=True) == "Acquiring"
        ca.put(P + "Acquire", 0)
        # the aborted frame's put completes, and says it failed
        assert done.wait(5) and outcome["status"].name == "ECA_PUTFAIL", outcome
        assert ca.get(P + "Status", as_string=True) == "Aborted" and ca.get(P + "Acquire") == 0
    finally:
        ca.put(P + "AcquireTime", 0.0)
    ca.put(P + "Acquire", 1, wait=True, timeout=60)
    assert ca.get(P + "Status", as_string=True) == "Idle"


# --------------------------------------------------------------------------- #
# robustness
# --------------------------------------------------------------------------- #
def test_ioc_keeps_serving_when_a_client_disconnects_mid_move(metrixs_ioc, ca, ca_tools):
    P, env = metrixs_ioc.prefix, metrixs_ioc.env
    rec = P + "e1:tz"
    velo = ca.get(rec + ".VELO")
    start = ca.get(rec + ".RBV")
    target = start + 0.3
    try:
        ca.put(rec + ".VELO", 0.3)  # a 1 s move
        client = subprocess.Popen([ca_tools["caproto-put"], "--no-repeater", "-c", "-w", "30", rec, str(target)],
                                  env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10
        while ca.get(rec + ".DMOV") == 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ca.get(rec + ".MOVN") == 1, "the move did not start"
        client.kill()  # the client vanishes with its put-completion pending
        client.wait(5)
        time.sleep(0.2)
        mid = ca.get(rec + ".RBV")
        assert start < mid < target
        deadline = time.monotonic() + 10
        while ca.get(rec + ".DMOV") == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ca.get(rec + ".RBV") == pytest.approx(target, abs=1e-5)  # the move ran to its end
        ca.put(rec, start, wait=True)  # and the IOC still serves puts and reads (its 30 s timeout)
        assert ca.get(rec + ".RBV") == pytest.approx(start, abs=1e-5)
        assert metrixs_ioc.proc.poll() is None
    finally:
        ca.put(rec + ".VELO", velo)


READER = textwrap.dedent("""
    import json, sys, time
    import numpy as np
    from caproto import ChannelType
    from caproto.threading.client import Context
    P, duration = sys.argv[1], float(sys.argv[2])
    ctx = Context()
    names = ["ArrayCounter", "HistX", "HistY", "Image", "TotalCounts", "NumRays"]
    pvs = dict(zip(names, ctx.get_pvs(*[P + "chamber:" + n for n in names])))
    rbv, dmov, val = ctx.get_pvs(P + "e2:tz.RBV", P + "e2:tz.DMOV", P + "e2:tz.VAL")
    for pv in (*pvs.values(), rbv, dmov, val):
        pv.wait_for_connection(timeout=10)
    events, keep = [], []
    for pv, key in ((rbv, "rbv"), (dmov, "dmov"), (val, "val")):
        sub = pv.subscribe()
        cb = lambda s, r, key=key: events.append((key, float(r.data[0])))
        keep.append((sub, cb))  # caproto holds callbacks weakly
        sub.add_callback(cb)
    frames, t_end = [], time.monotonic() + duration
    while time.monotonic() < t_end:
        c1 = int(pvs["ArrayCounter"].read().data[0])
        vals = {n: np.asarray(pvs[n].read().data, float) for n in names[1:]}
        c2 = int(pvs["ArrayCounter"].read().data[0])
        if c1 == c2:
            frames.append({"counter": c1, **{k: v.tolist() for k, v in vals.items()}})
        time.sleep(0.01)
    time.sleep(0.3)
    print(json.dumps({"frames": frames, "events": events}))
""")


def test_second_client_reads_consistent_values_during_moves_and_frames(metrixs_ioc, ca, tmp_path):
    P = metrixs_ioc.prefix
    script = tmp_path / "reader.py"
    script.write_text(READER)
    reader = subprocess.Popen([sys.executable, str(script), P, "6"], env=metrixs_ioc.env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    rec = P + "e2:tz"
    start = ca.get(rec + ".RBV")
    mres = ca.get(rec + ".MRES")
    time.sleep(1.5)  # let the reader connect
    try:
        for k, dz in enumerate((0.2, -0.1, 0.05, -0.15)):
            ca.put(rec, start + dz, wait=True)
            ca.put(P + "chamber:Acquire", 1, wait=True, timeout=60)
    finally:
        ca.put(rec, start, wait=True)
    out, err = reader.communicate(timeout=60)
    assert reader.returncode == 0, err
    data = json.loads(out)
    frames = [f for f in data["frames"] if f["counter"] > 0]
    assert len({f["counter"] for f in frames}) >= 3, "the reader should have seen several frames"
    for f in frames:  # histograms, image and count of one frame belong together
        hx, hy, img = np.array(f["HistX"]), np.array(f["HistY"]), np.array(f["Image"]).reshape(50, 50)
        assert np.all(img.sum(axis=0) <= hx + 1e-12) and np.all(img.sum(axis=1) <= hy + 1e-12)
        assert hx.sum() * f["NumRays"][0] <= f["TotalCounts"][0] + 1e-6
    # motor: while moving the readback runs monotonically towards the target; at DMOV=1 it is there
    rbv = val = None
    segment: list[float] = []
    n_done = 0
    for key, v in data["events"]:
        if key == "val":
            val = v
        elif key == "rbv":
            rbv = v
            segment.append(v)
        elif key == "dmov" and v == 1 and rbv is not None and val is not None:
            assert abs(rbv - val) <= mres * 1.01
            steps = np.diff(segment)
            assert np.all(steps >= -mres) or np.all(steps <= mres)
            segment, n_done = [rbv], n_done + 1
    assert n_done >= 4


# --------------------------------------------------------------------------- #
# the surrogate backend (the twin is the default; issue 4 trains the real surrogate)
# --------------------------------------------------------------------------- #
def _small_surrogate(path):
    """A small surrogate checkpoint, trained with the surrogate module's own classes on a few
    twin traces near the centre of the box (where footprints are bright)."""
    import torch

    from bluesky_offsets.surrogate.network import Architecture, Normalization, Surrogate
    from bluesky_offsets.physics.twin import Twin
    rng = np.random.default_rng(0)
    x = 0.5 + rng.uniform(-0.01, 0.01, (24, len(METRIXS)))
    b = Twin(scheduler="inline").trace_batch(METRIXS.denormalize(x), n_rays=400, seed=0, progress=False)
    y = np.concatenate([b.hist_x, b.hist_y], axis=1)
    norm = Normalization.fit(METRIXS, y)
    model = Surrogate.new(Architecture(width=64, n_layers=3), norm)
    X = torch.as_tensor(x, dtype=torch.float32)
    Y = torch.as_tensor((y - norm.out_low) / norm.out_span, dtype=torch.float32)
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny batches: more threads only fight the other jobs
    try:
        opt = torch.optim.Adam(model.net.parameters(), lr=3e-3)
        for _ in range(150):
            opt.zero_grad()
            loss = ((model.net(X) - Y) ** 2).mean()
            loss.backward()
            opt.step()
    finally:
        torch.set_num_threads(threads)
    model.net.eval()
    return model.save(path)


def test_surrogate_backend_draws_finite_ray_noise(tmp_path):
    from sim_iocs.backends import make_backend
    path = _small_surrogate(tmp_path / "small.pt")
    backend = make_backend(f"surrogate:{path}")
    try:
        values = METRIXS.denormalize(np.full(len(METRIXS), 0.5))
        expected = np.asarray(backend.model.predict(values[None]))[0]
        n = 2000
        frames = [backend.submit(values, n).result(timeout=30) for _ in range(40)]
        hx = np.array([f.hist_x for f in frames])
        assert frames[0].image is None and all(np.isfinite(f.hist_y).all() for f in frames)
        np.testing.assert_allclose(hx * n, np.round(hx * n), atol=1e-9)  # whole rays
        b = int(np.argmax(expected[:50]))
        p = expected[b]
        assert abs(hx[:, b].mean() - p) < 5 * np.sqrt(p * (1 - p) / n / 40)
        assert 0.4 < hx[:, b].var() / (p * (1 - p) / n) < 2.5  # the ray budget's noise
        assert all(f.n_hits >= round(f.hist_x.sum() * n) for f in frames)
        dark = backend.submit(values, 0).result(timeout=30)
        assert dark.n_hits == 0 and not dark.hist_x.any()
    finally:
        backend.close()
    with pytest.raises(ValueError, match="cannot apply hidden physical effects other than the chamber"):
        make_backend(f"surrogate:{path}", overrides={"M1-Cylinder": {"slopeErrorSag": 1.0}})
    with pytest.raises(ValueError, match="trained without the focus chamber's inputs"):
        make_backend(f"surrogate:{path}", overrides={"ImagePlane": {"translationZerror": 1.0}})
    with pytest.raises(ValueError, match="does not exist"):
        make_backend(f"surrogate:{tmp_path / 'none.pt'}")


def test_motor_dynamics_follow_the_range(metrixs_ioc, ca):
    """Every axis crosses its whole travel in the configured move time (0.5 s in the tests);
    the travel is the box except for the slit openings."""
    for p in METRIXS:
        if p.motorized:
            rec = metrixs_ioc.prefix + p.device.replace(".", ":")
            lo, hi = p.limits
            assert ca.get(rec + ".VELO") == pytest.approx((hi - lo) / 0.5), p.name
            assert (ca.get(rec + ".LLM"), ca.get(rec + ".HLM")) == pytest.approx((lo, hi)), p.name
            assert ca.get(rec + ".VMAX") >= ca.get(rec + ".VELO")
            assert ca.get(rec + ".EGU", as_string=True) == p.unit


def test_seeded_truth_is_dumped_not_published(ioc_factory, tmp_path, ca):
    from conftest import METRIXS_IOC_ARGS
    dump, seed = tmp_path / "truth-11.json", tmp_path / "seed"
    seed.write_text("11\n")
    ioc = ioc_factory(args=["--seed-file", seed, "--max-offset", 0.05, "--dump-truth", dump, *METRIXS_IOC_ARGS],
                      ready="chamber:Message", ready_value="ready", timeout=90)
    truth = Truth.from_file(dump)
    # the clients' environment it prints names the port it serves on
    assert f"EPICS_CA_ADDR_LIST=127.0.0.1:{ioc.port} EPICS_CA_AUTO_ADDR_LIST=NO" in ioc.log()
    assert np.abs(truth.offsets).max() <= 0.05 and np.count_nonzero(truth.offsets) == 34
    assert ca.get(ioc.prefix + "chamber:TruthId", as_string=True) == truth.truth_id
    np.testing.assert_array_equal(truth.offsets, Truth.from_seed(11, limit=0.05).offsets)
    assert ca.get(ioc.prefix + "e2:rz.RBV") == pytest.approx(27.0)  # the start position, no offset added
