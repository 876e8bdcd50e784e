"""The compose test (``make compose-test``; not part of ``make test``: it needs a Docker
engine). Builds the image, brings docker-compose.yml up with the host-network override
(deploy/compose.host.yml) on an unusual loopback port, waits for every container's health
check, checks a planner's answers from this host, checks that every keyframe the frontend
selected is in the map, restarts the mapper and checks it resumes (its keyframes from the
checkpoint volume, a newer epoch, the query service answering with the new map), and
brings the stack down (volume included).

``--tls``: the same over the TLS profile (deploy/tls/compose.tls.yml, certificates made by
deploy/tls/make-certs.sh in deploy/tls/certs, the default namespace the access control
names); the planner and the checks connect with the planner's and the monitor's
certificates, and a client without a certificate must not connect.

Environment: AISDF_ZENOH_PORT (default 37447), AISDF_TORCH_FIND_LINKS (a URL or folder,
reachable from the build, holding a CPU wheel of torch, for machines that cannot reach
download.pytorch.org; a local folder is served on 127.0.0.1 for the build), AISDF_NO_BUILD=1
to use an image already built, COMPOSE (default: ``docker compose``, else ``docker-compose``).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from aisdf import keys, protocol, query_messages, transport
from aisdf.config import ZenohOptions
from aisdf.stack import free_port, wait_for

ROOT = Path(__file__).resolve().parents[1]
PORT = int(os.environ.get("AISDF_ZENOH_PORT", "37447"))
NS = "aisdf/composetest"
PROJECT = "aisdf-compose-test"
T0 = time.monotonic()


def say(msg: str) -> None:
    print(f"[{time.monotonic() - T0:6.1f} s] {msg}", flush=True)


def compose_cmd() -> list[str]:
    if os.environ.get("COMPOSE"):
        return shlex.split(os.environ["COMPOSE"])
    ok = subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0
    return ["docker", "compose"] if ok else ["docker-compose"]


TLS = "--tls" in sys.argv[1:]
if TLS:
    NS, PROJECT = "aisdf", PROJECT + "-tls"
COMPOSE = compose_cmd() + ["-p", PROJECT, "-f", "docker-compose.yml", "-f", "deploy/compose.host.yml"]
COMPOSE += ["-f", "deploy/tls/compose.tls.yml"] if TLS else []
ENV = {**os.environ, "AISDF_ZENOH_PORT": str(PORT), "AISDF_NAMESPACE": NS, "AISDF_ZENOH_PROTO": "tls" if TLS else "tcp"}


def run(cmd: list[str], check: bool = True, quiet: bool = False) -> subprocess.CompletedProcess:
    p = subprocess.run(cmd, cwd=ROOT, env=ENV, capture_output=True, text=True)
    if check and p.returncode != 0:
        raise SystemExit(f"FAILED: {' '.join(cmd)}\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
    return p


def build() -> None:
    links = os.environ.get("AISDF_TORCH_FIND_LINKS", "")
    server = None
    if links and Path(links).is_dir():  # serve a local folder to the build (host network)
        port = free_port()
        server = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
                                  cwd=links, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        links = f"http://127.0.0.1:{port}/"
        time.sleep(1.0)
    try:
        cmd = ["docker", "build", "--network", "host", "-t", "aisdf:latest", "."]
        if links:
            cmd[2:2] = ["--build-arg", f"TORCH_FIND_LINKS={links}"]
        say("building: " + " ".join(cmd))
        run(cmd)
    finally:
        if server:
            server.terminate()
            server.wait(10)


def health(service: str) -> str:
    cid = run(COMPOSE + ["ps", "-q", service]).stdout.strip()
    if not cid:
        return "absent"
    p = run(["docker", "inspect", "--format", "{{if .State.Health}}{{.State.Health.Status}}{{end}}/{{.State.Status}}",
             cid], check=False)
    return p.stdout.strip()


def info(session, name: str):
    return transport.get_latest(session, keys.key(NS, f"info/{name}"), 2.0)


def answer(session):
    try:
        return transport.query(session, keys.key(NS, keys.QUERY_SDF),
                               query_messages.SdfRequest(np.array([[1.0, 1.0, 1.0], [2.0, 1.5, 1.0]])).to_msg(), 5.0)
    except (protocol.ProtocolError, TimeoutError):
        return None


def client_options() -> tuple[ZenohOptions, ZenohOptions]:
    """(planner, monitor) Zenoh options: plain TCP, or the TLS profile's identities."""
    if not TLS:
        opts = ZenohOptions(mode="client", connect=[f"tcp/127.0.0.1:{PORT}"], multicast_scouting=False)
        return opts, opts
    certs = ROOT / "deploy/tls/certs"
    run(["bash", "deploy/tls/make-certs.sh", str(certs)])
    out = []
    for name in ("planner", "monitor"):
        text = (ROOT / f"deploy/tls/{name}.json5").read_text().replace("/etc/aisdf/tls", str(certs))
        path = certs / f"compose-test-{name}.json5"
        path.write_text(text.replace("tls/zenoh:7447", f"tls/127.0.0.1:{PORT}"))
        out.append(ZenohOptions(config_file=path))
    return out[0], out[1]


def refused_without_certificate() -> bool:
    opts = ZenohOptions(mode="client", connect=[f"tls/127.0.0.1:{PORT}", f"tcp/127.0.0.1:{PORT}"],
                        multicast_scouting=False)
    try:
        with transport.open_session(opts) as s:
            time.sleep(0.5)
            return not list(s.info.routers_zid())
    except Exception:  # noqa: BLE001 - ZError: no endpoint accepted the session
        return True


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tls", action="store_true", help="over the TLS profile (deploy/tls)")
    p.parse_args()
    planner_opts, monitor_opts = client_options()
    if os.environ.get("AISDF_NO_BUILD") != "1":
        build()
    size = run(["docker", "image", "inspect", "aisdf:latest", "--format", "{{.Size}}"]).stdout.strip()
    say(f"image aisdf:latest: {int(size) / 1e9:.2f} GB")
    assert int(size) <= 1.2e9, "the image is above 1.2 GB"
    run(COMPOSE + ["down", "-v"], check=False)
    try:
        say(f"up: router on {'tls' if TLS else 'tcp'}/127.0.0.1:{PORT}, namespace {NS}")
        run(COMPOSE + ["up", "-d", "--no-build"])
        services = ("zenoh", "mapper", "query", "frontend")
        states = wait_for(lambda: (lambda s: s if all(v.startswith("healthy") for v in s.values()) else None)(
            {n: health(n) for n in services}), 240, period=2.0, what="every container healthy")
        say(f"healthy: {states}")
        if TLS:
            assert refused_without_certificate(), "a client without a certificate connected"
            say("a client without a certificate (TLS or plain TCP): refused")
        with transport.open_session(planner_opts) as planner, transport.open_session(monitor_opts) as s:
            r = wait_for(lambda: answer(planner), 180, period=1.0, what="a planner's answer")
            sdf = ", ".join(f"{x:.3f}" for x in protocol.decode_array(r["sdf"], "sdf"))
            say(f"planner: sdf [{sdf}] m from map version "
                f"{r['map_version']} (epoch {r.get('map_epoch')}, baked {r.get('baked')})")
            # every keyframe the frontend selected is in the map
            logs = wait_for(lambda: (lambda t: t if " done: " in t else None)(
                run(COMPOSE + ["logs", "--no-color", "frontend"]).stdout), 240, period=2.0, what="the frontend done")
            m = re.search(r"done: (\d+) frames, (\d+) keyframes; (\d+) acknowledged.*?(\d+) dropped while held", logs)
            frames, selected, acked, dropped = map(int, m.groups())
            mi = info(s, "mapper")
            say(f"frontend: {frames} frames, {selected} keyframes selected, {acked} acknowledged, {dropped} dropped; "
                f"mapper: {mi['keyframes']} keyframes in the map, version {mi['version']}, epoch {mi['epoch']}")
            assert selected > 0 and acked == selected == mi["keyframes"] and dropped == 0
            wait_for(lambda: any(p.name == "mapper-checkpoint.pt" for p in [Path(x) for x in run(
                COMPOSE + ["exec", "-T", "mapper", "ls", "/var/lib/aisdf"]).stdout.split()]), 90, period=2.0,
                     what="the mapper's checkpoint")
            time.sleep(1.0)
            before = info(s, "mapper")
            say(f"restarting the mapper (version {before['version']}, epoch {before['epoch']}, "
                f"{before['keyframes']} keyframes)")
            t = time.monotonic()
            run(COMPOSE + ["restart", "mapper"])
            say(f"restart command done in {time.monotonic() - t:.1f} s (the mapper checkpoints as it stops)")
            t = time.monotonic()
            resumed = wait_for(lambda: (lambda i: i if i and i["epoch"] > before["epoch"] else None)(info(s, "mapper")),
                               120, period=1.0, what="the restarted mapper")
            r = wait_for(lambda: (lambda a: a if a and a.get("map_epoch", 0) == resumed["epoch"] else None)(answer(planner)),
                         120, period=0.5, what="answers from the restarted mapper's map")
            say(f"mapper resumed: epoch {resumed['epoch']}, version {resumed['version']}, {resumed['keyframes']} "
                f"keyframes; planner answered from map version {r['map_version']} (epoch {r['map_epoch']}) "
                f"{time.monotonic() - t:.1f} s after the restart")
            assert resumed["keyframes"] == before["keyframes"] and resumed["version"] > before["version"]
            wait_for(lambda: health("mapper").startswith("healthy"), 60, period=2.0, what="the mapper healthy again")
            say(f"mapper healthy again: {health('mapper')}")
    finally:
        run(COMPOSE + ["logs", "--no-color", "--tail", "5"], check=False)
        p = run(COMPOSE + ["down", "-v"], check=False)
        say(f"down: exit {p.returncode}")
    say("compose test PASSED")


if __name__ == "__main__":
    main()
