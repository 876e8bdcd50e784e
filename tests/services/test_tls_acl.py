"""The TLS profile (deploy/tls), end to end on loopback: a router (``aisdf-router``) with
deploy/tls/router.json5 (TLS only, mutual authentication, access control by certificate
common name), the real frontend, mapper and query services with their own certificates
and deploy/tls/<service>.json5, certificates made by deploy/tls/make-certs.sh. Only the
certificate paths and the port are changed from the shipped files.

Without a certificate (or with one from another CA, or over plain TCP) nothing connects; a
planner that publishes keyframes or maps changes nothing; a planner gets answers, and follows
the query replicas (protocol 1.12), which only the query identity can announce."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from aisdf import keys, protocol, query_messages, transport
from aisdf.client import SdfClient
from aisdf.config import ZenohOptions
from aisdf.replicas import Replicas
from aisdf.stack import free_port, wait_for
from aisdf.synthetic import SyntheticSequence

pytestmark = [pytest.mark.e2e, pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")]
TLS = Path(__file__).resolve().parents[2] / "deploy" / "tls"
NS = "aisdf"  # router.json5's access control names keys under the default namespace
SERVICES = {"mapper": ["-m", "aisdf_mapper.main", "--preset", "cpu", "--set", "training.network.width=32"],
            "query": ["-m", "aisdf_query.main"],
            "frontend": ["-m", "aisdf_frontend.main", "--set", "n_frames=120", "--set", "width=80", "--set", "height=60",
                         "--set", "linger=true", "--set", "resend_period_s=2"]}


def write_config(name: str, certs: Path, port: int, out: Path) -> Path:
    text = (TLS / f"{name}.json5").read_text()
    text = text.replace("/etc/aisdf/tls", str(certs)).replace("tls/zenoh:7447", f"tls/localhost:{port}")
    text = text.replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")
    path = out / f"{name}.json5"
    path.write_text(text)
    return path


def opts(path: Path) -> ZenohOptions:
    return ZenohOptions(config_file=path)


def plain_config(out: Path, name: str, conf: dict) -> Path:
    path = out / f"{name}.json5"
    path.write_text(json.dumps({"mode": "client", "scouting": {"multicast": {"enabled": False}}, **conf}))
    return path


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tls")
    certs, rogue = tmp / "certs", tmp / "rogue"
    for d in (certs, rogue):
        subprocess.run(["bash", str(TLS / "make-certs.sh"), str(d)], check=True, capture_output=True)
    port = free_port()
    conf = {n: write_config(n, certs, port, tmp) for n in ("router", "frontend", "mapper", "query", "planner", "monitor")}
    procs, logs = {}, []
    env = {"OMP_NUM_THREADS": "1", **os.environ, "PYTHONUNBUFFERED": "1"}

    def start(name, args):
        log = open(tmp / f"{name}.log", "w")  # noqa: SIM115 - closed below
        logs.append(log)
        procs[name] = subprocess.Popen([sys.executable, *args, "--namespace", NS, "--zenoh-config", str(conf[name])],
                                       stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)

    start("router", ["-c", "from aisdf.ops import router_cli; router_cli()"])
    try:
        wait_for(lambda: connects(conf["monitor"]), 30, what="the router")
        with transport.open_session(opts(conf["monitor"])) as mon:
            for name in ("mapper", "query", "frontend"):
                start(name, SERVICES[name])
            wait_for(lambda: transport.get_latest(mon, keys.key(NS, "info/mapper"), 1.0), 90, what="the mapper")
            yield {"tmp": tmp, "certs": certs, "rogue": rogue, "port": port, "conf": conf, "monitor": mon,
                   "procs": procs}
    finally:
        for p in reversed(list(procs.values())):
            p.terminate()
        for p in procs.values():
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
        for log in logs:
            log.close()


def connects(path: Path) -> bool:
    """Whether a client with this Zenoh configuration gets a session with the router."""
    try:
        with transport.open_session(opts(path)) as s:
            time.sleep(0.5)
            return bool(list(s.info.routers_zid()))
    except Exception:  # noqa: BLE001 - zenoh raises ZError when no endpoint accepts it
        return False


def info(d, name):
    return transport.get_latest(d["monitor"], keys.key(NS, f"info/{name}"), 2.0)


def sdf_answer(session):
    try:
        return transport.query(session, keys.key(NS, keys.QUERY_SDF), query_messages.SdfRequest(np.zeros((8, 3))).to_msg(),
                               5.0)
    except (protocol.ProtocolError, TimeoutError):
        return None


def test_without_a_valid_certificate_nothing_connects(deployment):
    d, tmp, port = deployment, deployment["tmp"], deployment["port"]
    no_cert = plain_config(tmp, "no-cert", {"connect": {"endpoints": [f"tls/localhost:{port}"]},
                                            "transport": {"link": {"tls": {"root_ca_certificate": str(d["certs"] / "ca.pem")}}}})
    plain_tcp = plain_config(tmp, "plain-tcp", {"connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})
    other_ca = write_config("planner", d["rogue"], port, tmp / "rogue")  # a planner certificate from another CA
    other_ca_trusting = plain_config(tmp, "rogue-trusting", {  # ... even trusting the right CA
        "connect": {"endpoints": [f"tls/localhost:{port}"]},
        "transport": {"link": {"tls": {"root_ca_certificate": str(d["certs"] / "ca.pem"), "enable_mtls": True,
                                       "connect_certificate": str(d["rogue"] / "frontend.pem"),
                                       "connect_private_key": str(d["rogue"] / "frontend.key")}}}})
    results = {n: connects(p) for n, p in [("no certificate", no_cert), ("plain TCP", plain_tcp),
                                            ("certificate from another CA", other_ca),
                                            ("another CA's frontend certificate", other_ca_trusting),
                                            ("planner certificate", d["conf"]["planner"])]}
    print("connects:", results)
    assert results == {"no certificate": False, "plain TCP": False, "certificate from another CA": False,
                       "another CA's frontend certificate": False, "planner certificate": True}


def test_planner_gets_answers_and_reads_maps(deployment):
    d = deployment
    with transport.open_session(opts(d["conf"]["planner"])) as planner:
        r = wait_for(lambda: sdf_answer(planner), 120, period=1.0, what="a planner's query/sdf answer")
        got = []
        sub = planner.declare_subscriber(keys.key(NS, "map/**"), lambda s: got.append(str(s.key_expr)))
        weights = transport.get_latest(planner, keys.key(NS, keys.MAP_INDEX), 3.0)  # the map (1.3: submaps)
        wait_for(lambda: got, 10, what="a map snapshot on the planner's subscriber")
        sub.undeclare()
        print(f"planner: answered by map version {r['map_version']} (epoch {r.get('map_epoch')}); "
              f"got map/index version {weights and weights['version']}; subscriber saw {sorted(set(got))}")
        assert r["sdf"]["shape"] == [8] and r["map_version"] >= 1
        assert weights is not None and weights["version"] >= 1
        # ... and nothing else: not the services' info, not the keyframes
        assert transport.get_latest(planner, keys.key(NS, "info/mapper"), 1.5) is None
    # the real frontend streamed through the access control, and every keyframe was acknowledged
    fi = wait_for(lambda: (lambda i: i if i and i["done"] and i["pending"] == 0 else None)(info(d, "frontend")), 60,
                  what="the frontend's keyframes acknowledged")
    print(f"frontend: {fi['keyframes']} keyframes, {fi['acked']} acknowledged")
    assert fi["keyframes"] > 0 and fi["acked"] == fi["keyframes"]


def health(conf: Path, service: str, *extra: str) -> int:
    return subprocess.run([sys.executable, "-c", "from aisdf.ops import health_cli; health_cli()", service,
                           "--zenoh-config", str(conf), "--timeout", "2", *extra], capture_output=True,
                          timeout=60).returncode


def test_health_checks_with_each_service_identity(deployment):
    conf = deployment["conf"]
    codes = {name: health(conf[name], name) for name in ("mapper", "query", "frontend")}
    codes["router"] = health(conf["mapper"], "router")
    codes["planner sees mapper"] = health(conf["planner"], "mapper")  # status/** is not a planner's
    # a query replica checks its own token: the service here has the default id <this host>-<hex>
    rid = info(deployment, "query")["replica"]
    assert rid.startswith(keys.host_chunk() + "-")
    codes["query --own-host"] = health(conf["query"], "query", "--own-host")
    codes["query --id-prefix <its id>"] = health(conf["query"], "query", "--id-prefix", rid)
    codes["query --id-prefix elsewhere-"] = health(conf["query"], "query", "--id-prefix", "elsewhere-")
    codes["query --id-prefix a/*"] = health(conf["query"], "query", "--id-prefix", "a/*")  # usage error
    codes["query --id <its id>"] = health(conf["query"], "query", "--id", rid)
    codes["query --id <its id less a char>"] = health(conf["query"], "query", "--id", rid[:-1])  # not a prefix
    print(f"aisdf-health exit codes (query replica {rid}):", codes)
    assert codes == {"mapper": 0, "query": 0, "frontend": 0, "router": 0, "planner sees mapper": 1,
                     "query --own-host": 0, "query --id-prefix <its id>": 0, "query --id-prefix elsewhere-": 1,
                     "query --id-prefix a/*": 2, "query --id <its id>": 0, "query --id <its id less a char>": 1}


def test_planner_follows_the_query_replica(deployment):
    """Protocol 1.12 under the access control: a planner's (and a monitor's) SdfClient sees the
    query service's replica token and its requests are answered on the replica's own key."""
    d = deployment
    rid = info(d, "query")["replica"]
    sdf_key = keys.replica_key(NS, rid, "sdf")
    req = query_messages.SdfRequest(np.zeros((8, 3))).to_msg()
    with SdfClient(namespace=NS, zenoh=opts(d["conf"]["planner"]), timeout=10.0) as c:
        # (SdfClient's first liveliness get can end before its subscriber's history arrives: wait)
        seen = wait_for(lambda: c.replica_ids(), 10, period=0.1, what="the replica at the planner")
        wait_for(lambda: sdf_answer(c._session), 120, period=1.0, what="a planner's query/sdf answer")
        e0 = info(d, "query")["evaluated"]
        r = c.query(np.zeros((8, 3)))
        direct = transport.query(c._session, sdf_key, req, 5.0)  # the replica's key itself answers a planner
        e1 = info(d, "query")["evaluated"]
        print(f"planner: replicas seen {seen}; answered by map version {r.map_version}; on {sdf_key}: "
              f"map version {direct['map_version']}; evaluated {e0} -> {e1}")
        assert seen == [rid] and c.replica_ids() == [rid]
        assert r.sdf.shape == (8,) and direct["sdf"]["shape"] == [8] and e1 == e0 + 2
    with transport.open_session(opts(d["conf"]["monitor"])) as mon:
        reps = Replicas(mon, NS)
        try:
            seen = wait_for(lambda: reps.ids(), 10, period=0.1, what="the replica at the monitor")
            print(f"monitor: replicas seen {seen}")
            assert seen == [rid]
        finally:
            reps.close()


def keyframe_msg(frame_id: int, sensor: str) -> dict:
    f = SyntheticSequence(building="atlanta", n_frames=30, H=60, W=80, seed=3).frame(10)
    return protocol.Keyframe(frame_id, f["stamp"], f["depth"].astype(np.float32), f["K"], f["T_WC"],
                             sensor=sensor).to_msg()


def test_planner_publishing_keyframes_or_maps_changes_nothing(deployment):
    d = deployment
    key_kf = keys.key(NS, keys.KEYFRAMES)
    wait_for(lambda: (lambda i: i and i["pending"] == 0)(info(d, "mapper")), 60, what="the mapper idle")
    with transport.open_session(opts(d["conf"]["planner"])) as planner, \
            transport.open_session(opts(d["conf"]["frontend"])) as frontend:
        overheard = []
        sub = planner.declare_subscriber(  # (a session also hears its own puts, locally)
            key_kf, lambda s: overheard.append(protocol.unpack(transport.payload_bytes(s.payload))["frame_id"]))
        time.sleep(1.0)
        before = info(d, "mapper")
        for i in range(3):
            transport.put(planner, key_kf, keyframe_msg(900_000 + i, "intruder"))
        time.sleep(3.0)
        after_planner = info(d, "mapper")
        print(f"mapper before: received {before['received']}, keyframes {before['keyframes']}; after a planner "
              f"published 3 keyframes: received {after_planner['received']}, keyframes {after_planner['keyframes']}")
        assert after_planner["received"] == before["received"]
        assert after_planner["keyframes"] == before["keyframes"]
        # the same keyframe from the frontend identity does arrive (so the check above can fail) ...
        transport.put(frontend, key_kf, keyframe_msg(910_000, "frontend-check"))
        after = wait_for(lambda: (lambda i: i if i["received"] > before["received"] else None)(info(d, "mapper")), 15,
                         what="the frontend identity's keyframe at the mapper")
        print(f"after the frontend identity published 1: received {after['received']}")
        assert after["received"] == before["received"] + 1
        time.sleep(0.5)
        sub.undeclare()
        assert 910_000 not in overheard  # ... and a planner cannot overhear keyframes

        # maps: only the mapper's reach the query service (not a planner's, the frontend's, a
        # monitor's or the query identity's own)
        q0 = info(d, "query")
        # a forged map: one of the mapper's submaps and an index listing it, from a far future
        index = transport.get_latest(d["monitor"], keys.key(NS, keys.MAP_INDEX), 3.0)
        sid = next(iter(index["submaps"]))
        sub = transport.get_latest(d["monitor"], keys.key(NS, f"{keys.MAP_SUBMAPS}/{sid}"), 3.0)
        sub["version"], sub["epoch"] = 10**9, 10**15
        index.update(version=10**9, epoch=10**15, submaps={sid: {"version": 10**9, "step": sub["step"]}})

        def forge(session):
            transport.put(session, keys.key(NS, f"{keys.MAP_SUBMAPS}/{sid}"), sub)
            transport.put(session, keys.key(NS, keys.MAP_INDEX), index)

        for s in (planner, frontend, d["monitor"]):
            forge(s)
        with transport.open_session(opts(d["conf"]["query"])) as query:  # it reads maps, never writes them
            forge(query)
            time.sleep(3.0)
        q1 = info(d, "query")
        print(f"query service map version before/after forged maps: {q0['version']} / {q1['version']}")
        assert q1["version"] < 10**9 and q1["epoch"] < 10**15
        # the same forged map from the mapper identity is taken (so the check above can fail)
        with transport.open_session(opts(d["conf"]["mapper"])) as mapper:
            forge(mapper)
            q2 = wait_for(lambda: (lambda i: i if i["version"] == 10**9 else None)(info(d, "query")), 10,
                          what="the mapper identity's map at the query service")
        print(f"after the same map from the mapper identity: {q2['version']}")


FORGED_M = 42.0
# An impostor: another process (as on another machine) with an identity's Zenoh settings, that
# declares query/sdf and answers every request with a forged reply (every distance 42 m: all
# clear) a planner would steer by, until it is terminated. (Told apart by its distances, not its
# map version: the test above leaves the real service with a forged map of version 10**9.) With a
# replica id, it declares that replica's sdf key (complete) and then its token, as a 1.12 replica.
IMPOSTOR = """
import sys, time
from pathlib import Path
import numpy as np
from aisdf import keys, protocol, query_messages, transport
from aisdf.config import ZenohOptions

def on_query(q):
    rep = query_messages.SdfReply(1, np.full(8, FORGED, np.float32))
    q.reply(q.key_expr, protocol.pack(rep.to_msg()), encoding=transport.ENCODING)

with transport.open_session(ZenohOptions(config_file=Path(sys.argv[1]))) as s:
    rid = sys.argv[3] if len(sys.argv) > 3 else None
    key = keys.replica_key(sys.argv[2], rid, "sdf") if rid else keys.key(sys.argv[2], keys.QUERY_SDF)
    decl = s.declare_queryable(key, on_query, complete=rid is not None)
    token = s.liveliness().declare_token(keys.replica_key(sys.argv[2], rid)) if rid else None
    print("declared", flush=True)
    time.sleep(600)
""".replace("FORGED", repr(FORGED_M))


def impostor(conf: Path, rid: str | None = None) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", IMPOSTOR, str(conf), NS, *([rid] if rid else [])],
                         stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "declared"
    return p


def all_answers(session) -> list[str]:
    """Every reply to one query/sdf request, from every queryable: "forged" or "real"."""
    import zenoh

    req = protocol.pack(query_messages.SdfRequest(np.zeros((8, 3))).to_msg())
    out = []
    for r in session.get(keys.key(NS, keys.QUERY_SDF), payload=req, encoding=transport.ENCODING,
                         target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0):
        if r.ok is not None:
            sdf = query_messages.SdfReply.from_msg(protocol.unpack(transport.payload_bytes(r.ok.payload))).sdf
            out.append("forged" if np.all(sdf == FORGED_M) else "real")
    return out


def test_only_the_query_identity_can_answer_planners(deployment):
    """A planner or a monitor that declares query/sdf to answer in the query service's place
    reaches nobody: a planner hears only the real service. The same impostor with the query
    identity is heard (so the check can fail)."""
    conf = deployment["conf"]
    with transport.open_session(opts(conf["planner"])) as asker:
        wait_for(lambda: sdf_answer(asker), 120, period=1.0, what="a planner's query/sdf answer")
        for identity in ("planner", "monitor"):
            p = impostor(conf[identity])
            try:
                time.sleep(1.0)  # its declaration would have reached the router and the planner
                heard = all_answers(asker) + all_answers(asker)
            finally:
                p.kill()
                p.wait()
            print(f"a {identity} answering query/sdf: the planner heard {heard}")
            assert heard == ["real", "real"], (identity, heard)
        p = impostor(conf["query"])
        try:
            wait_for(lambda: "forged" in all_answers(asker), 15, period=0.5,
                     what="the query identity's impostor at the planner")
        finally:
            p.kill()
            p.wait()


def forged_on(session, rid: str) -> bool | None:
    """What ``rid``'s replica key answers a planner: True forged, False real, None nothing."""
    try:
        r = transport.query(session, keys.replica_key(NS, rid, "sdf"),
                            query_messages.SdfRequest(np.zeros((8, 3))).to_msg(), 2.0)
    except (protocol.ProtocolError, TimeoutError):
        return None
    return bool(np.all(query_messages.SdfReply.from_msg(r).sdf == FORGED_M))


def test_only_the_query_identity_can_announce_a_replica(deployment):
    """A frontend (a robot's) or a planner that declares a replica token and its queryables
    reaches nobody: a planner's SdfClient sees only the real replica, and the impostor's replica
    key answers nothing. The same impostor with the query identity is seen and answers (so the
    check can fail)."""
    d = deployment
    rid = info(d, "query")["replica"]
    with transport.open_session(opts(d["conf"]["planner"])) as planner:
        reps = Replicas(planner, NS)
        try:
            for identity in ("frontend", "planner"):
                fake = f"impostor-{identity}"
                p = impostor(d["conf"][identity], fake)
                try:
                    time.sleep(1.0)  # its declarations would have reached the router and the planner
                    with SdfClient(namespace=NS, zenoh=opts(d["conf"]["planner"])) as fresh:
                        wait_for(lambda: rid in fresh.replica_ids(), 10, period=0.1, what="the real replica")
                        seen = (reps.ids(), fresh.replica_ids(), forged_on(planner, fake))
                finally:
                    p.kill()
                    p.wait()
                print(f"a {identity} announcing replica {fake}: the planner saw {seen[0]} (a new client: {seen[1]}); "
                      f"its replica key answered {seen[2]}")
                assert seen == ([rid], [rid], None), (identity, seen)
            p = impostor(d["conf"]["query"], "impostor-query")
            try:
                wait_for(lambda: "impostor-query" in reps.ids(), 15, period=0.2,
                         what="the query identity's replica token at the planner")
                assert forged_on(planner, "impostor-query") is True
            finally:
                p.kill()
                p.wait()
            wait_for(lambda: reps.ids() == [rid], 15, period=0.2, what="the impostor's token gone")
        finally:
            reps.close()
