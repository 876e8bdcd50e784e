"""Two small commands for deployments.

``aisdf-router``: a Zenoh router from a JSON5 configuration (the TLS profile's router,
with its access control, in deploy/tls/router.json5; the tests run the same). zenohd does
the same with ``-c FILE``; this one needs nothing beyond the services' image.

``aisdf-health SERVICE``: exit 0 when a service's liveliness token
(``<namespace>/status/<service>/*``) is on the Zenoh network, 1 when not; ``router`` checks
that a router answers. The containers' health checks run it with the service's own Zenoh
configuration. ``--id ID`` counts only the token with exactly that id, ``--id-prefix P`` those
whose id starts with ``P``, ``--own-host`` those of this host's query replicas (``<host>-``,
their default ids): with several query replicas or mapper slots (``docker compose up --scale
query=2 --scale mapper=3``) each container checks its own (``--id``: ``mapper-1`` must not
take ``mapper-10`` for itself), not any.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time

import zenoh

from . import keys, transport
from .config import ServiceConfig, add_common_args, config_from_args, service_setup

log = logging.getLogger("aisdf.router")


def run_router(cfg: ServiceConfig, stop: threading.Event) -> None:
    """A Zenoh session in router mode until ``stop`` is set."""
    conf = transport.zenoh_config(cfg.zenoh)
    conf.insert_json5("mode", '"router"')
    with zenoh.open(conf) as session:
        log.info("router %s up (namespace of the services: %s)", session.zid(), cfg.namespace)
        stop.wait()


def router_cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="aisdf-router", description="A Zenoh router from a JSON5 configuration "
                                "(--zenoh-config), e.g. deploy/tls/router.json5: TLS, mutual authentication and "
                                "access control. Runs until SIGINT/SIGTERM.")
    add_common_args(p)
    args = p.parse_args(argv)
    cfg = config_from_args(ServiceConfig, args)
    run_router(cfg, service_setup(cfg, "router"))


def healthy(cfg: ServiceConfig, service: str, timeout: float = 3.0, id_prefix: str = "",
            exact: bool = False) -> bool:
    """Whether a ``service`` liveliness token ``status/<service>/<id>`` with an id starting with
    ``id_prefix`` (``exact``: equal to it) is seen (``router``: whether a router is connected)."""
    conf = transport.zenoh_config(cfg.zenoh)
    with zenoh.open(conf) as session:
        end = time.monotonic() + timeout
        while True:
            if service == "router":
                if list(session.info.routers_zid()):
                    return True
            else:
                for reply in session.liveliness().get(keys.status_key(cfg.namespace, service, "*"),
                                                      timeout=max(0.1, end - time.monotonic())):
                    if reply.ok is None:
                        continue
                    rid = str(reply.ok.key_expr).rsplit("/", 1)[-1]
                    if rid == id_prefix if exact else rid.startswith(id_prefix):
                        return True
            if time.monotonic() >= end:
                return False
            time.sleep(0.2)


def health_cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="aisdf-health", description="Exit 0 when SERVICE's liveliness token "
                                "(<namespace>/status/SERVICE/*) is on the Zenoh network, 1 when not; SERVICE "
                                "'router': when a router is connected. For containers' health checks.")
    p.add_argument("service", help="frontend, mapper, query, or router")
    p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait (default 3)")
    own = p.add_mutually_exclusive_group()
    own.add_argument("--id", default="", help="only the token with exactly this id (status/SERVICE/<id>)")
    own.add_argument("--id-prefix", default="", help="only a token whose id (status/SERVICE/<id>) starts with this")
    own.add_argument("--own-host", action="store_true", help="only this host's query replicas: --id-prefix "
                     "'<host>-', the start of their default ids (in a container: the container's hostname)")
    add_common_args(p)
    args = p.parse_args(argv)
    if args.service == "router" and (args.id or args.id_prefix or args.own_host):
        p.error("--id, --id-prefix and --own-host are for services' tokens, not 'router'")
    prefix = f"{keys.host_chunk()}-" if args.own_host else args.id or args.id_prefix
    if any(c in prefix for c in "/*$?#"):
        p.error(f"invalid {'--id' if args.id else '--id-prefix'} {prefix!r}: part of one key chunk, no '/' or wildcards")
    cfg = config_from_args(ServiceConfig, args)
    logging.basicConfig(level=logging.WARNING)
    ok = healthy(cfg, args.service, args.timeout, prefix, exact=bool(args.id))
    shown = f" {prefix}" if args.id else f" {prefix}*" if prefix else ""
    print(f"{args.service}{shown}: {'healthy' if ok else 'not seen'}")
    sys.exit(0 if ok else 1)
