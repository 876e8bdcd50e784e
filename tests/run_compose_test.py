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

``--scaled``: shards and replicas instead of the restart, ``AISDF_MAPPER_SHARDS=true`` and
``--scale mapper=3 --scale query=2`` (host networking: every container has the host's name):
each mapper container holds its own slot (the lock and the journal its process has open are
slot-<n>'s, its id mapper-<n>), every mapper lists all three as members, both query replicas
announce themselves (``status/query/<id>``, ``query/replica/<id>``, the id the container's
health check reads) and answer a request sent to each, a planner's ``SdfClient`` gets a map's
answer through the router, and every keyframe the frontend selected is held by a mapper. Then
it restarts the container of slot 2 and checks it comes back as mapper-2 on slot 2.
``--tls --scaled``: the same over the TLS profile.

Environment: AISDF_ZENOH_PORT (default 37447), AISDF_TORCH_FIND_LINKS (a URL or folder,
reachable from the build, holding a CPU wheel of torch, for machines that cannot reach
download.pytorch.org; a local folder is served on 127.0.0.1 for the build), AISDF_NO_BUILD=1
to use an image already built, COMPOSE (default: ``docker compose``, else ``docker-compose``).
"""

from __future__ import annotations

import argparse
import json
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
SCALED = "--scaled" in sys.argv[1:]
if TLS:
    NS, PROJECT = "aisdf", PROJECT + "-tls"
SCALE = {"zenoh": 1, "mapper": 3, "query": 2, "frontend": 1} if SCALED else dict.fromkeys(
    ("zenoh", "mapper", "query", "frontend"), 1)
if SCALED:
    PROJECT += "-scaled"
COMPOSE = compose_cmd() + ["-p", PROJECT, "-f", "docker-compose.yml", "-f", "deploy/compose.host.yml"]
COMPOSE += ["-f", "deploy/tls/compose.tls.yml"] if TLS else []
ENV = {**os.environ, "AISDF_ZENOH_PORT": str(PORT), "AISDF_NAMESPACE": NS, "AISDF_ZENOH_PROTO": "tls" if TLS else "tcp"}
if SCALED:
    ENV["AISDF_MAPPER_SHARDS"] = "true"


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


def containers(service: str) -> list[str]:
    return run(COMPOSE + ["ps", "-q", service]).stdout.split()


def health_of(cid: str) -> str:
    p = run(["docker", "inspect", "--format", "{{if .State.Health}}{{.State.Health.Status}}{{end}}/{{.State.Status}}",
             cid], check=False)
    return p.stdout.strip()


def health(service: str) -> str:
    cids = containers(service)
    return health_of(cids[0]) if cids else "absent"


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


def check_single(planner_opts, monitor_opts) -> None:
    """A planner's answer, the frontend's keyframes in the map, the mapper restarted and resumed."""
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tls", action="store_true", help="over the TLS profile (deploy/tls)")
    p.add_argument("--scaled", action="store_true", help="AISDF_MAPPER_SHARDS=true, --scale mapper=3 --scale query=2: "
                   "slots, members, replicas, a planner's answer, the keyframes, one mapper restarted")
    p.parse_args()
    planner_opts, monitor_opts = client_options()
    if os.environ.get("AISDF_NO_BUILD") != "1":
        build()
    size = run(["docker", "image", "inspect", "aisdf:latest", "--format", "{{.Size}}"]).stdout.strip()
    say(f"image aisdf:latest: {int(size) / 1e9:.2f} GB")
    assert int(size) <= 1.2e9, "the image is above 1.2 GB"
    run(COMPOSE + ["down", "-v"], check=False)
    try:
        scale = [a for n, k in SCALE.items() if k > 1 for a in ("--scale", f"{n}={k}")]
        say(f"up: router on {'tls' if TLS else 'tcp'}/127.0.0.1:{PORT}, namespace {NS} {' '.join(scale)}")
        t_up = time.monotonic()
        run(COMPOSE + ["up", "-d", "--no-build", *scale])
        say(f"up command done in {time.monotonic() - t_up:.1f} s (it waits for the health checks the order needs)")
        if SCALED:
            wait_healthy_scaled(t_up)
        else:
            services = ("zenoh", "mapper", "query", "frontend")
            states = wait_for(lambda: (lambda s: s if all(v.startswith("healthy") for v in s.values()) else None)(
                {n: health(n) for n in services}), 240, period=2.0, what="every container healthy")
            say(f"healthy: {states}")
        if TLS:
            assert refused_without_certificate(), "a client without a certificate connected"
            say("a client without a certificate (TLS or plain TCP): refused")
        if SCALED:
            with transport.open_session(monitor_opts) as s:
                check_scaled(s, planner_opts)
        else:
            check_single(planner_opts, monitor_opts)
    finally:
        run(COMPOSE + ["logs", "--no-color", "--tail", "5"], check=False)
        p = run(COMPOSE + ["down", "-v"], check=False)
        say(f"down: exit {p.returncode}")
    say("compose test PASSED")


# ---------------------------------------------------------------------------- --scaled

def wait_healthy_scaled(t_up: float) -> None:
    """Every container of every service healthy (as many as SCALE says); prints each one's
    seconds from ``up`` to its first healthy state."""
    first: dict[str, float] = {}

    def poll():
        ok = True
        for n, k in SCALE.items():
            cids = containers(n)
            ok &= len(cids) == k
            for c in cids:
                if health_of(c).startswith("healthy"):
                    first.setdefault(f"{n}:{c[:12]}", time.monotonic() - t_up)
                else:
                    ok = False
        return ok or None

    wait_for(poll, 300, period=2.0, what="every container healthy")
    say("healthy (s after up): " + ", ".join(f"{k} {v:.1f}" for k, v in sorted(first.items())))


def health_output(cid: str) -> str:
    """The last output of the container's health check."""
    log = json.loads(run(["docker", "inspect", "--format", "{{json .State.Health.Log}}", cid]).stdout or "null")
    return log[-1]["Output"].strip() if log else ""


def slot_of(cid: str) -> tuple[int, list[str]]:
    """(the slot whose lock the container's process 1 holds, the journals it has open)."""
    fds = run(["docker", "exec", cid, "ls", "-l", "/proc/1/fd"]).stdout
    locks = re.findall(r"-> /var/lib/aisdf/slot-(\d+)/lock$", fds, re.M)
    assert len(locks) == 1, f"container {cid[:12]}: slot locks {locks}"
    return int(locks[0]), re.findall(r"-> (\S+/mapper-journal\.bin)$", fds, re.M)


def all_members(s, want: set[str], what: str) -> dict[str, dict]:
    """info/mapper of each mapper, once the mappers are ``want`` and each lists them all as members."""
    from aisdf.bench.cluster import mapper_infos

    seen = {}

    def ok():
        i = mapper_infos(s, NS)
        seen.update(last={k: v["cluster"]["members"] for k, v in i.items()})
        return i if set(i) == want and all(set(m) == want for m in seen["last"].values()) else None

    try:
        return wait_for(ok, 120, period=1.0, what=what)
    except TimeoutError as e:
        raise SystemExit(f"FAILED: {e}; mappers answering info/mapper and their members: {seen.get('last')}") from None


def check_scaled(s, planner_opts) -> None:
    from aisdf.bench.cluster import mapper_infos
    from aisdf.client import SdfClient

    # each mapper container its own slot, its own journal, its id mapper-<n>, all three members
    want = {f"mapper-{n}" for n in range(1, SCALE["mapper"] + 1)}
    infos = all_members(s, want, "every mapper listing all members")
    say("mappers: " + "; ".join(f"{k} members {v['cluster']['members']}" for k, v in sorted(infos.items())))
    slots = {}
    for c in containers("mapper"):
        n, journals = slot_of(c)
        p = run(["docker", "logs", c])
        logs = p.stdout + p.stderr
        assert f"state in /var/lib/aisdf/slot-{n} (slot {n})" in logs, f"container {c[:12]} slot {n}: no log line"
        assert all(j == f"/var/lib/aisdf/slot-{n}/mapper-journal.bin" for j in journals), (c, n, journals)
        assert health_output(c) == f"mapper mapper-{n}: healthy", (c, n, health_output(c))  # its own token
        slots[n] = (c, journals)
    say("slots: " + "; ".join(f"slot-{n} held by container {c[:12]} (mapper-{n}), journal open: "
                              f"{', '.join(j) or 'none yet'}" for n, (c, j) in sorted(slots.items())))
    assert sorted(slots) == list(range(1, SCALE["mapper"] + 1)), sorted(slots)
    files = run(["docker", "exec", slots[1][0], "sh", "-c", "cd /var/lib/aisdf && ls -d slot-*/*"]).stdout.split()
    say(f"the volume: {' '.join(sorted(files))}")

    # two query replicas: their tokens, the ids their health checks read, an answer from each
    ids = []
    for c in containers("query"):
        ids.append(run(["docker", "exec", c, "cat", "/tmp/aisdf-replica-id"]).stdout.strip())
        assert health_output(c) == f"query {ids[-1]}: healthy", (c, health_output(c))  # its own token
    ids.sort()
    tokens = sorted(str(r.ok.key_expr).rsplit("/", 1)[-1] for r in
                    s.liveliness().get(keys.status_key(NS, "query", "*"), timeout=2.0) if r.ok is not None)
    say(f"query replicas: container ids {ids}; status/query tokens {tokens}")
    assert len(set(ids)) == SCALE["query"] and tokens == ids, (ids, tokens)
    pts = np.array([[1.0, 1.0, 1.0], [2.0, 1.5, 1.0]])
    req = query_messages.SdfRequest(pts).to_msg()

    def direct(rid):
        try:
            return transport.query(s, keys.replica_key(NS, rid, "sdf"), req, 5.0)
        except (protocol.ProtocolError, TimeoutError):
            return None

    for rid in ids:
        r = wait_for(lambda: direct(rid), 180, period=1.0, what=f"replica {rid}'s answer")
        say(f"replica {rid}: sdf {np.round(protocol.decode_array(r['sdf'], 'sdf').astype(float), 3).tolist()} m, "
            f"map version {r['map_version']}")

    # a planner through the router, with the client library
    # (timeout 30 s: on 2 cores three mappers train beside the replicas, which bake each new map)
    with SdfClient(NS, zenoh=planner_opts, timeout=30.0) as c:
        wait_for(lambda: sorted(c.replica_ids()) == ids or None, 30, period=0.5, what="the client seeing both replicas")
        replies, took = [], []
        for _ in range(10):
            t = time.monotonic()
            replies.append(c.query(pts))
            took.append(time.monotonic() - t)
        say(f"planner (SdfClient): replicas {sorted(c.replica_ids())}; 10 requests answered, each in "
            f"{min(took):.2f}..{max(took):.2f} s (median {np.median(took):.2f}), the last: sdf "
            f"{np.round(replies[-1].sdf.astype(float), 3).tolist()} m, map version {replies[-1].map_version}, baked "
            f"{replies[-1].baked}; failovers {c.failovers}")
        assert all(np.isfinite(r.sdf).all() and r.map_version > 0 for r in replies)

    # every keyframe the frontend selected is held by a mapper (each by two: ranks 1 and 2)
    logs = wait_for(lambda: (lambda t: t if " done: " in t else None)(
        run(COMPOSE + ["logs", "--no-color", "frontend"]).stdout), 300, period=2.0, what="the frontend done")
    m = re.search(r"done: (\d+) frames, (\d+) keyframes; (\d+) acknowledged.*?(\d+) dropped while held, "
                  r"(\d+) never acknowledged", logs)
    frames, selected, acked, dropped, pending = map(int, m.groups())
    infos = mapper_infos(s, NS)
    held = set().union(*({tuple(k) for k in i["keys"]} for i in infos.values()))
    say(f"frontend: {frames} frames, {selected} keyframes selected, {acked} acknowledged, {dropped} dropped, "
        f"{pending} never acknowledged; mappers hold {len(held)} distinct keyframes ("
        + ", ".join(f"{k} {v['keyframes']}" for k, v in sorted(infos.items())) + ")")
    assert selected > 0 and acked == selected == len(held) and dropped == pending == 0

    # a restarted container takes its slot again: the same id, the same directory
    c2, before = slots[2][0], infos["mapper-2"]["keyframes"]
    run(["docker", "restart", c2])
    t = time.monotonic()
    wait_for(lambda: health_of(c2).startswith("healthy"), 180, period=2.0, what="slot 2's container healthy again")
    n, _ = slot_of(c2)
    infos = all_members(s, want, "every mapper listing all members again")
    say(f"restarted slot 2's container: healthy {time.monotonic() - t:.1f} s later, holds slot-{n}, "
        f"mapper-2 back with {infos['mapper-2']['keyframes']} keyframes "
        f"({before} before)")
    assert n == 2 and infos["mapper-2"]["keyframes"] == before, (n, infos["mapper-2"]["keyframes"], before)


if __name__ == "__main__":
    main()
