"""Two small commands for deployments.

``aisdf-router``: a Zenoh router from a JSON5 configuration (the TLS profile's router,
with its access control, in deploy/tls/router.json5; the tests run the same). zenohd does
the same with ``-c FILE``; this one needs nothing beyond the services' image.

``aisdf-health SERVICE``: exit 0 when a service's liveliness token
(``<namespace>/status/<service>/*``) is on the Zenoh network, 1 when not; ``router`` checks
that a router answers. The containers' health checks run it with the service's own Zenoh
configuration.
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


def healthy(cfg: ServiceConfig, service: str, timeout: float = 3.0) -> bool:
    """Whether a ``service`` liveliness token is seen (``router``: whether a router is connected)."""
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
                    if reply.ok is not None:
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
    add_common_args(p)
    args = p.parse_args(argv)
    cfg = config_from_args(ServiceConfig, args)
    logging.basicConfig(level=logging.WARNING)
    ok = healthy(cfg, args.service, args.timeout)
    print(f"{args.service}: {'healthy' if ok else 'not seen'}")
    sys.exit(0 if ok else 1)
