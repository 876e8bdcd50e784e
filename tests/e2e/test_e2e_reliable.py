"""End to end, protocol 1.2: no keyframe lost when the mapper starts late or dies, and a
restarted mapper's map reaches planners within seconds. Real processes over real Zenoh on
loopback (explicit endpoints, multicast scouting off); the mapper is killed with SIGKILL."""

import json
import time

import numpy as np
import pytest

from aisdf import keys, protocol, query_messages, transport
from aisdf.stack import Stack, wait_for

pytestmark = pytest.mark.e2e
NS = "aisdf/e2e12"
MAPPER = ["--preset", "cpu", "--set", "training.network.width=32", "--set", "log_level=INFO"]


def frontend_args(n_frames):
    # 30 fps at the sensor's rate: n_frames / 30 seconds of streaming; linger to answer info.
    return ["--set", f"n_frames={n_frames}", "--set", "width=80", "--set", "height=60", "--set", "linger=true",
            "--set", "resend_period_s=2"]


def info(session, name):
    return transport.get_latest(session, keys.key(NS, f"info/{name}"), 2.0)


def kill(st, name):
    p = st.procs[name]
    p.kill()  # SIGKILL: no clean shutdown, no last checkpoint
    p.wait(10)


def settled(session):
    """Frontend and mapper info once the source is done and nothing is unacknowledged."""
    fi, mi = info(session, "frontend"), info(session, "mapper")
    if fi and mi and fi["done"] and fi["pending"] == 0 and mi["pending"] == 0:
        return fi, mi
    return None


def check_counts(fi, mi, what):
    print(f"{what}: frontend selected {fi['keyframes']} keyframes, {fi['acked']} acknowledged, "
          f"{fi['sent']} sent, {fi['resent']} resent, {fi['dropped']} dropped while held, {fi['rejected']} rejected; "
          f"mapper has {mi['keyframes']} keyframes in the map ({mi['seen']} seen; this incarnation received "
          f"{mi['received']}, accepted {mi['accepted']}, {mi['duplicates']} duplicates, {mi['dropped']} dropped, "
          f"{mi['rejected']} rejected)")
    assert fi["keyframes"] > 5
    assert fi["acked"] == fi["keyframes"] and fi["dropped"] == 0 and fi["rejected"] == 0
    assert mi["keyframes"] == fi["keyframes"] == mi["seen"]  # every keyframe, none twice


def test_mapper_started_10_s_after_the_frontend_gets_every_keyframe():
    st = Stack(services=("mapper", "frontend"), namespace=NS, args={"mapper": MAPPER, "frontend": frontend_args(360)})
    try:
        st.start(["frontend"])
        with transport.open_session(st.client_zenoh) as s:
            wait_for(lambda: info(s, "frontend"), 60, what="the frontend")
            time.sleep(10.0)
            fi = info(s, "frontend")
            print(f"after 10 s without a mapper: {fi['frames']} frames, {fi['keyframes']} keyframes held, "
                  f"{fi['sent']} sent")
            assert fi["keyframes"] > 0 and fi["sent"] == 0 and fi["pending"] == fi["keyframes"]
            st.start(["mapper"])
            fi, mi = wait_for(lambda: settled(s), 120, what="every keyframe acknowledged")
            check_counts(fi, mi, "mapper started 10 s late")
    finally:
        st.stop()


def test_mapper_killed_mid_run_resumes_without_loss_or_duplicates(tmp_path):
    args = MAPPER + ["--checkpoint-dir", str(tmp_path), "--set", "checkpoint_period_s=4"]
    st = Stack(services=("mapper", "frontend"), namespace=NS, args={"mapper": args, "frontend": frontend_args(540)})
    try:
        st.start(["mapper"])
        with transport.open_session(st.client_zenoh) as s:
            wait_for(lambda: info(s, "mapper"), 60, what="the mapper")
            st.start(["frontend"])
            wait_for(lambda: (lambda i: i and i["accepted"] >= 4 and (tmp_path / "mapper-checkpoint.pt").exists())(
                info(s, "mapper")), 60, what="keyframes and a checkpoint")
            time.sleep(1.5)
            before = info(s, "mapper")
            kill(st, "mapper")
            time.sleep(3.0)  # the frontend holds what it selects meanwhile
            fi = info(s, "frontend")
            print(f"killed with {before['keyframes']} keyframes in the map; frontend: {fi['keyframes']} selected, "
                  f"{fi['pending']} unacknowledged")
            st.start(["mapper"])
            fi, mi = wait_for(lambda: settled(s), 120, what="every keyframe acknowledged")
            check_counts(fi, mi, "mapper killed and restarted")
            assert mi["epoch"] > before["epoch"] and mi["version"] > before["version"]
    finally:
        st.stop()


def query_version(s):
    try:
        r = transport.query(s, keys.key(NS, keys.QUERY_SDF), query_messages.SdfRequest(np.zeros((4, 3))).to_msg(), 5.0)
    except (protocol.ProtocolError, TimeoutError):
        return None
    return r


def test_restarted_mapper_map_reaches_planners_within_30_s(tmp_path):
    """Killed 1 s and 25 s into its 30 s checkpoint period, the restarted mapper's map is
    what the query service answers with within 30 s of the restart: measured 3.6 and 5.5 s on
    a quiet machine, 6.5 and 4.2 s on 2 shared CPU cores (2026-12-05), 10.6 s in a compose run
    under load (README); the bound is 5x the quiet figures, so that load alone does not fail it."""
    period = 30.0
    args = MAPPER + ["--checkpoint-dir", str(tmp_path), "--set", f"checkpoint_period_s={period}"]
    st = Stack(services=("query", "mapper", "frontend"), namespace=NS,
               args={"mapper": args, "frontend": frontend_args(240)})
    ckpt = tmp_path / "mapper-checkpoint.pt"
    try:
        st.start()
        with transport.open_session(st.client_zenoh) as s:
            started = time.monotonic()
            wait_for(lambda: ckpt.exists(), period + 60, what="the first checkpoint")
            delays = {}
            for into_period in (1.0, 25.0):
                # The period started at the last checkpoint (the first run) or at the start (a restarted mapper).
                t_ref = ckpt.stat().st_mtime if into_period == 1.0 else started
                now_wall = time.time() if into_period == 1.0 else time.monotonic()
                time.sleep(max(0.0, t_ref + into_period - now_wall))
                held = wait_for(lambda: query_version(s), 30, what="a query answer")
                kill(st, "mapper")
                last = json.loads((tmp_path / "mapper-incarnation.json").read_text())
                restarted = started = time.monotonic()
                st.start(["mapper"])
                new = {}

                def answered_by_the_new_mapper():
                    r = query_version(s)
                    if r is None or r["map_version"] <= last["version"]:
                        return None
                    new.update(info(s, "mapper") or {})
                    return r

                r = wait_for(answered_by_the_new_mapper, 60, period=0.25, what="the restarted mapper's map")
                delays[into_period] = time.monotonic() - restarted
                print(f"killed {into_period:.0f} s into the period: query held version {held['map_version']}, the "
                      f"dead mapper had published up to version {last['version']} (epoch {last['epoch']}); "
                      f"answered with version {r['map_version']}"
                      f"{' epoch ' + str(r['map_epoch']) if 'map_epoch' in r else ''} from the new mapper "
                      f"(epoch {new.get('epoch')}) {delays[into_period]:.1f} s after the restart")
                assert new.get("epoch", 0) > last["epoch"]
                if "map_epoch" in r:
                    assert r["map_epoch"] == new["epoch"]
            assert all(d < 30.0 for d in delays.values()), delays
    finally:
        st.stop()


def test_services_stop_when_the_process_that_started_them_is_killed(tmp_path):
    """A demo or a test run killed outright (SIGKILL: a CI time limit, an operator) leaves no
    service behind holding its port and cores: each service watches the process that started it
    and stops cleanly (exit code 0, mapper checkpoint written) once it is gone."""
    import os
    import signal
    import subprocess
    import sys

    ckpt = tmp_path / "ckpt"
    script = (
        "import sys, time\n"
        "from aisdf.stack import Stack\n"
        f"st = Stack(args={{'mapper': {MAPPER + ['--checkpoint-dir', str(ckpt)]!r}, "
        f"'frontend': {frontend_args(60)!r}}}, log_dir={str(tmp_path / 'logs')!r}).start()\n"
        "print(' '.join(str(p.pid) for p in st.procs.values()), flush=True)\n"
        "time.sleep(600)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(x) for x in parent.stdout.readline().split()]
        assert len(pids) == 3, pids

        def running(pid):
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return False
            # re-parented to this test's process tree or init: a zombie is not running
            with open(f"/proc/{pid}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] != "Z"

        assert all(running(p) for p in pids)
        time.sleep(8.0)  # the services are up (the mapper has a map to checkpoint)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        wait_for(lambda: not any(running(p) for p in pids), 60, what="the orphaned services to stop")
        logs = {p.stem: p.read_text() for p in (tmp_path / "logs").glob("*.log")}
        for name in ("query", "mapper", "frontend"):
            assert "parent process" in logs[name] and "is gone: stopping" in logs[name], logs[name][-2000:]
        # written on a clean stop (the periodic one is every 30 s, beyond this run)
        assert (ckpt / "mapper-checkpoint.pt").is_file(), sorted(p.name for p in ckpt.iterdir())
    finally:
        if parent.poll() is None:
            parent.kill()
        for p in locals().get("pids", []):
            try:
                os.kill(p, signal.SIGKILL)
            except ProcessLookupError:
                pass
