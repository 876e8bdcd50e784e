"""Start the three services as separate processes on loopback (the demo, the benchmark
and the end-to-end tests use this; ``docker compose`` does the same across containers).

Every process listens on its own loopback port and connects to the others', with
multicast scouting off, so nothing leaves the machine and start order does not matter.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from .config import PARENT_ENV, ZenohOptions

SERVICES = {"query": "aisdf_query.main", "mapper": "aisdf_mapper.main", "frontend": "aisdf_frontend.main"}


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Stack:
    """``with Stack(args={"mapper": [...]}) as st: st.client_zenoh ...``"""

    def __init__(self, services=("query", "mapper", "frontend"), namespace: str = "aisdf",
                 args: dict[str, list[str]] | None = None, log_dir: str | Path | None = None,
                 env: dict[str, str] | None = None, ports: dict[str, int] | None = None):
        self.services = list(services)
        self.namespace = namespace
        self.args = args or {}
        self.log_dir = Path(log_dir) if log_dir else None
        self.env = env or {}
        self.ports = ports or {s: free_port() for s in self.services}
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list = []

    @property
    def endpoints(self) -> list[str]:
        return [endpoint(p) for p in self.ports.values()]

    @property
    def client_zenoh(self) -> ZenohOptions:
        """Zenoh options for a client in this process (connects to every service)."""
        return ZenohOptions(mode="peer", connect=self.endpoints, multicast_scouting=False)

    def command(self, name: str) -> list[str]:
        # a second instance of a service is named with a number: "frontend2" (a second robot)
        module = SERVICES.get(name) or SERVICES[name.rstrip("0123456789")]
        cmd = [sys.executable, "-m", module, "--namespace", self.namespace, "--no-multicast-scouting",
               "--listen", endpoint(self.ports[name])]
        for other, port in self.ports.items():
            if other != name:
                cmd += ["--connect", endpoint(port)]
        return cmd + list(self.args.get(name, []))

    def start(self, only: list[str] | None = None) -> "Stack":
        # One BLAS/OpenMP thread per service unless told otherwise: on a small machine
        # the three processes otherwise oversubscribe the cores (spinning threads).
        # The services stop when this process dies, however it dies (config.service_setup).
        env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               **os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid()), **self.env}
        for name in only or self.services:
            out = subprocess.DEVNULL
            if self.log_dir:
                self.log_dir.mkdir(parents=True, exist_ok=True)
                out = open(self.log_dir / f"{name}.log", "w")  # noqa: SIM115 - closed in stop()
                self._logs.append(out)
            self.procs[name] = subprocess.Popen(self.command(name), stdout=out, stderr=subprocess.STDOUT, env=env,
                                                start_new_session=True)
        return self

    def alive(self, name: str) -> bool:
        p = self.procs.get(name)
        return p is not None and p.poll() is None

    def stop_one(self, name: str, timeout: float = 15.0) -> int | None:
        p = self.procs.get(name)
        if p is None:
            return None
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        return p.returncode

    def stop(self) -> dict[str, int | None]:
        codes = {name: self.stop_one(name) for name in reversed(list(self.procs))}
        for f in self._logs:
            f.close()
        self._logs.clear()
        return codes

    def __enter__(self) -> "Stack":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def wait_for(predicate, timeout: float, period: float = 0.2, what: str = "condition"):
    """Poll ``predicate()`` until it returns a truthy value; raise TimeoutError after ``timeout``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = predicate()
        if v:
            return v
        time.sleep(period)
    raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
