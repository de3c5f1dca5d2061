"""The simulated beamline under bad input: every put completes, nothing non-finite is
published, aborts stop the work, and the hidden truth stays hidden (all against the real
IOC on loopback, through caproto's client)."""

import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import METRIXS_IOC_ARGS, start_metrixs_ioc

from sim_iocs.metrixs import MAX_RAYS
from sim_iocs.motor_record import MAX_ACCEL_TIME, STEPS_MAX
from sim_iocs.ports import free_port, stop_process_group

NAN, INF = float("nan"), float("inf")
BAD_MOTOR_PUTS = [("", NAN), (".DVAL", INF), (".RLV", NAN), (".TWV", INF), (".OFF", NAN), (".HLM", NAN),
                  (".LLM", -INF), (".DHLM", NAN), (".DLLM", INF), (".VELO", NAN), (".VELO", INF), (".VELO", 0.0),
                  (".VMAX", NAN), (".VBAS", -1.0), (".HVEL", NAN), (".ACCL", NAN), (".ACCL", INF),
                  (".MRES", NAN), (".MRES", 0.0), (".ERES", NAN), (".RRES", INF), (".RDBD", NAN), (".UREV", NAN)]
PUBLISHED = ("", ".RBV", ".DVAL", ".DRBV", ".DIFF", ".OFF", ".HLM", ".LLM", ".DHLM", ".DLLM", ".VELO", ".VMAX",
             ".VBAS", ".HVEL", ".ACCL", ".MRES", ".TWV")


def _failed(response) -> bool:
    return response.status.name == "ECA_PUTFAIL"


def _children(pid: int) -> set[int]:
    out = subprocess.run(["ps", "-ww", "--ppid", str(pid), "-o", "pid=,args="], capture_output=True, text=True).stdout
    return {int(line.split()[0]) for line in out.splitlines() if "spawn_main" in line}


def test_bad_motor_puts_are_refused_and_every_put_completes(metrixs_ioc, ca):
    rec = metrixs_ioc.prefix + "e1:tz"
    saved = {f: ca.get(rec + f) for f in (".VELO", ".ACCL", ".TWV")}
    start = ca.get(rec + ".RBV")
    try:
        for field, value in BAD_MOTOR_PUTS:
            assert _failed(ca.put(rec + field, value, wait=True, timeout=10)), f"{field} = {value} accepted"
        for field in PUBLISHED:
            assert math.isfinite(ca.get(rec + field)), f"{field} is not finite"
        ca.put(rec + ".SET", "Set")
        try:  # redefining the position to NaN is refused too
            assert _failed(ca.put(rec, NAN, wait=True, timeout=10))
        finally:
            ca.put(rec + ".SET", "Use")
        assert math.isfinite(ca.get(rec + ".OFF")) and math.isfinite(ca.get(rec + ".RBV"))
        ca.put(rec + ".ACCL", 1e6)  # minutes for a short move: clamped
        assert ca.get(rec + ".ACCL") == pytest.approx(MAX_ACCEL_TIME)
        ca.put(rec + ".ACCL", saved[".ACCL"])
        # the record still moves, and its put completes
        assert not _failed(ca.put(rec, start + 0.05, wait=True, timeout=30))
        assert ca.get(rec + ".DMOV") == 1 and ca.get(rec + ".RBV") == pytest.approx(start + 0.05, abs=1e-4)
    finally:
        for field, value in saved.items():
            ca.put(rec + field, value)
        ca.put(rec, start, wait=True, timeout=30)


def test_extreme_puts_keep_steps_limits_and_speeds_sane(metrixs_ioc, ca):
    """Issue 52's probe: a tiny MRES once hung a put-with-completion (the step count overflowed
    the 32-bit RRBV) or wrapped it silently; finite limits and offsets published infinities; a
    VELO of 1e-320 made a move that never ends, a negative one was made positive; VMAX lowered
    below VELO left VELO above it; text such as "1_0" was read as 10. Each refusal is one line
    in the IOC's log."""
    rec = metrixs_ioc.prefix + "e1:tz"
    saved = {f: ca.get(rec + f) for f in (".MRES", ".VELO", ".VMAX", ".DHLM", ".OFF", ".TWV", ".PREC")}
    start = ca.get(rec + ".RBV")
    try:
        ca.put(rec + ".MRES", 1e-20)
        assert not _failed(ca.put(rec, start + 0.01, wait=True, timeout=30))  # completes
        saturated = (STEPS_MAX, -STEPS_MAX - 1)
        assert ca.get(rec + ".DMOV") == 1 and ca.get(rec + ".RRBV") in saturated
        ca.put(rec + ".MRES", 1e-12)  # beyond 2**31 steps: saturated, not wrapped
        assert ca.get(rec + ".RVAL") in saturated
        ca.put(rec + ".MRES", saved[".MRES"])
        ca.put(rec + ".DHLM", 1e308)
        assert _failed(ca.put(rec + ".OFF", 1e308))  # the user high limit would be infinite
        assert math.isfinite(ca.get(rec + ".HLM")) and ca.get(rec + ".OFF") == saved[".OFF"]
        ca.put(rec + ".DHLM", saved[".DHLM"])
        for bad in (1e-320, -0.5):
            assert _failed(ca.put(rec + ".VELO", bad)), bad
        assert ca.get(rec + ".VELO") == saved[".VELO"]
        ca.put(rec + ".VMAX", saved[".VELO"] / 2)  # VELO follows VMAX down
        assert ca.get(rec + ".VELO") == pytest.approx(saved[".VELO"] / 2)
        for text in ("", "1_0", "0x10"):  # as text only a plain number (caproto read '' as 0, '1_0' as 10)
            assert _failed(ca.put(rec + ".TWV", text)), text
        assert not _failed(ca.put(rec + ".TWV", " 0.002 ")) and ca.get(rec + ".TWV") == 0.002
        chamber = metrixs_ioc.prefix + "chamber:"
        for pv, texts in ((rec + ".PREC", ("", "1_0", "2.5")), (rec + ".SREV", ("", "2_00")),
                          (chamber + "NumRays", ("", "1_000")), (chamber + "AcquireTime", ("", "1_0"))):
            before = ca.get(pv)
            for text in texts:  # integer fields: only a plain integer
                assert _failed(ca.put(pv, text)), (pv, text)
            assert ca.get(pv) == before, pv
        assert not _failed(ca.put(rec + ".PREC", " 5 ")) and ca.get(rec + ".PREC") == 5
    finally:
        for field in (".VMAX", ".VELO", ".MRES", ".DHLM", ".OFF", ".TWV", ".PREC"):
            ca.put(rec + field, saved[field])
        ca.put(rec, start, wait=True, timeout=30)
    log = metrixs_ioc.log()
    assert "refused put by" in log and "Traceback" not in log, log[-3000:]


def test_pause_and_stop_behave_like_the_record(metrixs_ioc, ca):
    rec = metrixs_ioc.prefix + "e1:ty"
    velo, start = ca.get(rec + ".VELO"), ca.get(rec + ".RBV")
    target = start + 0.4
    done = threading.Event()
    try:
        ca.put(rec + ".VELO", 0.4)  # a 1 s move
        threading.Thread(target=lambda: (ca.put(rec, target, wait=True, timeout=30), done.set()), daemon=True).start()
        deadline = time.monotonic() + 10
        while ca.get(rec + ".MOVN") == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        ca.put(rec + ".SPMG", "Pause")
        # paused mid-move: the axis stands, the move is not done
        assert ca.get(rec + ".MOVN") == 0 and ca.get(rec + ".DMOV") == 0 and not done.is_set()
        ca.put(rec + ".SPMG", "Go")
        assert done.wait(30)
        assert ca.get(rec + ".DMOV") == 1 and ca.get(rec + ".RBV") == pytest.approx(target, abs=1e-4)
        ca.put(rec + ".SPMG", "Stop")
        # with motion disabled a move is refused, not silently dropped
        assert _failed(ca.put(rec, start, wait=True, timeout=10))
        assert ca.get(rec) == pytest.approx(target, abs=1e-4)
    finally:
        ca.put(rec + ".SPMG", "Go")
        ca.put(rec + ".VELO", velo)
        ca.put(rec, start, wait=True, timeout=30)


def test_detector_settings_have_bounds(metrixs_ioc, ca):
    P = metrixs_ioc.prefix + "chamber:"
    rays, acquire_time = ca.get(P + "NumRays"), ca.get(P + "AcquireTime")
    for pv, value in (("NumRays", MAX_RAYS + 1), ("NumRays", -1), ("AcquireTime", INF), ("AcquireTime", NAN),
                      ("AcquireTime", -1.0), ("AcquireTime", 1e7)):
        assert _failed(ca.put(P + pv, value, wait=True, timeout=10)), f"{pv} = {value} accepted"
    assert ca.get(P + "NumRays") == rays and ca.get(P + "AcquireTime") == acquire_time


def test_abort_stops_the_tracing(metrixs_ioc, ca):
    """An abort stops the worker that traces (it is gone), the aborted put says so, and the
    next small frame is traced at once by the spare worker."""
    P = metrixs_ioc.prefix + "chamber:"
    pid = metrixs_ioc.proc.pid
    rays = ca.get(P + "NumRays")
    outcome = {}
    try:
        ca.put(P + "NumRays", MAX_RAYS)  # some 20 s of tracing on this machine
        before = _children(pid)
        thread = threading.Thread(target=lambda: outcome.update(r=ca.put(P + "Acquire", 1, wait=True, timeout=120)),
                                  daemon=True)
        thread.start()
        deadline = time.monotonic() + 10
        while ca.get(P + "Status", as_string=True) != "Acquiring" and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        ca.put(P + "Acquire", 0)
        thread.join(30)
        assert _failed(outcome["r"]) and ca.get(P + "Status", as_string=True) == "Aborted"
        after = _children(pid)
        gone = before - after
        assert gone, f"no frame worker was stopped: {before} -> {after}"
        counter = ca.get(P + "ArrayCounter")
        ca.put(P + "NumRays", 500)
        assert not _failed(ca.put(P + "Acquire", 1, wait=True, timeout=60))
        assert ca.get(P + "Status", as_string=True) == "Idle" and ca.get(P + "ArrayCounter") == counter + 1
        assert all(not Path(f"/proc/{p}").exists() for p in gone)
    finally:
        ca.put(P + "NumRays", rays)


def test_a_worker_that_died_while_idle_is_replaced(metrixs_ioc, ca):
    P = metrixs_ioc.prefix + "chamber:"
    for p in _children(metrixs_ioc.proc.pid):
        os.kill(p, 9)
    time.sleep(0.5)
    assert not _failed(ca.put(P + "Acquire", 1, wait=True, timeout=60))  # the first Acquire already works
    assert ca.get(P + "Status", as_string=True) == "Idle"


FRAME_PVS = ("Status", "TotalCounts", "Transmission", "HistX", "HistY", "Image", "ProfileX", "ProfileY")


def _dark_frame(ca, P):
    response = ca.put(P + "chamber:Acquire", 1, wait=True, timeout=60)
    out = {pv: ca.get(P + "chamber:" + pv, as_string=pv == "Status") for pv in FRAME_PVS}
    message = ca.get(P + "chamber:Message", as_string=True)
    counter = ca.get(P + "chamber:ArrayCounter")
    return response.status.name, out, message.replace(f"frame {counter}:", "frame N:")


def test_an_impossible_true_state_looks_like_any_dark_frame(tmp_path, ca):
    """A slit driven past closed by a hidden offset gives the frame a merely closed slit gives:
    no PV, message or put status tells them apart; the operator's truth log does."""
    log = tmp_path / "truth.log"
    # ASBL width offset -0.1 of its range: -0.02 mm
    ioc = start_metrixs_ioc(tmp_path, {"offsets": {"ASBL.totalWidth": -0.1}}, extra=("--truth-log", log))
    P, rec = ioc.prefix, ioc.prefix + "asbl:width"
    try:
        ca.put(rec + ".LLM", -1.0)
        ca.put(rec, 0.01, wait=True, timeout=30)  # true opening -0.01 mm: no slit can be that
        impossible = _dark_frame(ca, P)
        ca.put(rec, 0.02, wait=True, timeout=30)  # true opening 0: closed
        closed = _dark_frame(ca, P)
    finally:
        ioc.stop()
    assert impossible[0] == closed[0] == "ECA_NORMAL"
    assert impossible[2] == closed[2] and "ASBL" not in impossible[2]
    for pv in FRAME_PVS:
        np.testing.assert_array_equal(impossible[1][pv], closed[1][pv], err_msg=pv)
    assert impossible[1]["TotalCounts"] == 0
    assert "ASBL.totalWidth" in log.read_text()  # the operator's log names the cause
    assert "ASBL" not in ioc.log() and "-0.01" not in ioc.log()


def test_the_start_up_banner_and_truth_id_give_nothing_away(tmp_path, ca):
    from sim_iocs.truth import Truth
    from conftest import start_ioc
    dump, seed = tmp_path / "t.json", tmp_path / "seed"
    seed.write_text("4242")
    ioc = start_ioc("sim_iocs.metrixs", ["--seed-file", seed, "--dump-truth", dump, *METRIXS_IOC_ARGS],
                    log_dir=tmp_path, ready="chamber:Message", ready_value="ready", timeout=90)
    try:
        published = ca.get(ioc.prefix + "chamber:TruthId", as_string=True)
        assert b"4242" not in Path(f"/proc/{ioc.proc.pid}/cmdline").read_bytes()  # in no process list
    finally:
        ioc.stop()
    assert "4242" not in ioc.log() and "±" not in ioc.log()
    assert dump.stat().st_mode & 0o777 == 0o600  # the truth file: its owner's only
    # the seed on the command line is refused in one line
    refused = subprocess.run([sys.executable, "-m", "sim_iocs.metrixs", "--seed", "7"], capture_output=True,
                             text=True, timeout=60)
    assert refused.returncode == 2 and "--seed-file" in refused.stderr and len(refused.stderr.splitlines()) == 1
    truth = Truth.from_file(dump)
    assert published == truth.truth_id
    # the seed's offsets hashed without the secret salt do not give the published id
    assert Truth(truth.offsets).truth_id != published


def test_sigint_stops_the_ioc_even_when_its_parent_ignored_it(tmp_path):
    """A child inherits an ignored SIGINT (some test runners' workers ignore it): the IOC
    restores it, else its stopper waited 10 s before killing it."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        ioc = start_metrixs_ioc(tmp_path)
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        ioc.proc.send_signal(signal.SIGINT)
        assert ioc.proc.wait(5) == 0
    finally:
        ioc.stop()


def test_no_temporary_files_remain(tmp_path, monkeypatch, ca):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setenv("TMPDIR", str(scratch))
    ioc = start_metrixs_ioc(tmp_path)
    try:
        for _ in range(2):
            ca.put(ioc.prefix + "chamber:Acquire", 1, wait=True, timeout=60)
        for k in range(10):  # aborted within tens of ms of their start: RAYX's input held in memory
            ca.put(ioc.prefix + "chamber:Acquire", 1, wait=False)
            time.sleep(0.005 * k)
            ca.put(ioc.prefix + "chamber:Acquire", 0)
            assert not list(scratch.iterdir()), list(scratch.iterdir())
    finally:
        ioc.stop()
    assert not list(scratch.iterdir()), list(scratch.iterdir())


def test_beacons_go_to_loopback_only_without_epics_variables(tmp_path):
    """No EPICS_CAS_* variables: the IOC serves loopback and beacons to loopback, not
    255.255.255.255 (caproto's default)."""
    import caproto

    from sim_iocs.metrixs import _beacon_environment
    saved = {k: os.environ.pop(k, None) for k in ("EPICS_CAS_BEACON_ADDR_LIST", "EPICS_CAS_AUTO_BEACON_ADDR_LIST")}
    try:
        _beacon_environment(["127.0.0.1"])
        assert [a for a, _ in caproto.get_beacon_address_list()] == ["127.0.0.1"]
    finally:
        for k, v in saved.items():
            os.environ.pop(k, None)
            if v is not None:
                os.environ[k] = v
    # and the real IOC: its beacons arrive on loopback
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(30)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("EPICS_CAS")}
    env.update(EPICS_CA_SERVER_PORT=str(port), EPICS_CAS_BEACON_PORT=str(sink.getsockname()[1]),
               EPICS_CA_AUTO_ADDR_LIST="NO", EPICS_CA_ADDR_LIST=f"127.0.0.1:{port}")
    truth = tmp_path / "t.json"
    truth.write_text(json.dumps({"offsets": {}}))
    with open(tmp_path / "ioc.log", "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "sim_iocs.metrixs", "--prefix", "BCN:", "--truth", truth,
                                 *map(str, METRIXS_IOC_ARGS)], env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            data, sender = sink.recvfrom(1024)
            assert sender[0] == "127.0.0.1" and len(data) >= 16
        finally:
            stop_process_group(proc)
            sink.close()


def test_a_refused_beacon_is_one_line_once():
    """With no CA repeater listening, caproto logged each beacon's refusal with its traceback every
    15 s; the IOC says it once per address, in one line."""
    import logging

    from sim_iocs.metrixs import BeaconRefusedOnce
    f = BeaconRefusedOnce()

    def record():
        try:
            raise ConnectionRefusedError(111, "Connection refused")
        except OSError:
            import sys
            return logging.LogRecord("caproto.ctx", logging.ERROR, __file__, 1, "Failed to send beacon to %r. Try "
                                     "setting ...", (("127.0.0.1", 5065),), sys.exc_info())
    first, again = record(), record()
    assert f.filter(first) and first.exc_info is None and first.levelno == logging.WARNING
    assert "127.0.0.1" in first.getMessage() and "\n" not in first.getMessage()
    assert not f.filter(again)
    other = logging.LogRecord("caproto.ctx", logging.ERROR, __file__, 1, "something else", (), None)
    assert f.filter(other)


def test_a_frame_whose_worker_dies_is_traced_again():
    """Where rays are caught inside a toroid rayx 0.4.5 overruns its event buffer and its process
    often dies (Energize's demo on the camera lost its 36th frame so): the simulated beamline
    traces that frame again on a fresh worker with its noise drawn anew, and the operator's log
    says so.  Here the worker process is killed once it has the frame's job."""
    from bluesky_offsets.physics.parameters import METRIXS
    from sim_iocs.backends import TwinBackend

    backend = TwinBackend()
    try:
        worker = backend._worker()
        send = worker.conn.send

        def send_then_die(job):
            send(job)
            worker.proc.kill()
            worker.proc.join()

        worker.conn.send = send_then_die
        frame = backend._frame(METRIXS.reference.copy(), 2000, 1)
    finally:
        backend.close()
    assert frame.n_rays == 2000 and frame.n_hits > 0
    assert any(n.startswith("rayx failed") and "died" in n for n in backend.notes), backend.notes
