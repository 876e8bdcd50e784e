"""Packaging, entry points, compose file and image recipe (no Docker engine runs here)."""

import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_package_is_listed():
    pkgdir = PYPROJECT["tool"]["setuptools"]["package-dir"]
    found = set()
    for name, rel in pkgdir.items():
        base = ROOT / rel
        for init in base.rglob("__init__.py"):
            if "__pycache__" in init.parts:
                continue
            sub = init.parent.relative_to(base).parts
            found.add(".".join((name, *sub)))
    assert found == set(PYPROJECT["tool"]["setuptools"]["packages"])


def test_torch_requirement_admits_2_13_and_nothing_newer():
    req = next(r for r in PYPROJECT["project"]["dependencies"] if r.startswith("torch"))
    assert "<2.14" in req


@pytest.mark.parametrize("script", sorted(PYPROJECT["project"]["scripts"]))
def test_console_scripts_help_and_version(script):
    bindir = Path(sys.executable).parent
    for flag in ("--help", "--version"):
        r = subprocess.run([str(bindir / script), flag], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip()
    r = subprocess.run([str(bindir / script), "--version"], capture_output=True, text=True, timeout=60)
    assert re.search(r"\d+\.\d+\.\d+", r.stdout)


def test_compose_services_run_real_entry_points():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    scripts = PYPROJECT["project"]["scripts"]
    services = compose["services"]
    assert {"query", "mapper", "frontend"} <= set(services)
    bindir = Path(sys.executable).parent
    for name in ("query", "mapper", "frontend"):
        cmd = services[name]["command"]
        if cmd[:2] == ["sh", "-c"]:  # a shell that picks the replica id, then execs the service
            tail = cmd[2].split("exec ", 1)[1].replace("$$", "$")
            cmd = [a.replace("$id", "composetest-0a1b2c") for a in shlex.split(tail)]
        assert cmd[0] in scripts, f"{name}: {cmd[0]} is not a console script"
        # Run the exact command (with the container's paths mapped to the repo) up to its resolved config.
        args = [a.replace("/etc/aisdf/zenoh.json5", str(ROOT / "deploy/zenoh-client.json5"))
                 .replace("/var/lib/aisdf", "/tmp/aisdf-compose-test") for a in cmd[1:]]
        r = subprocess.run([str(bindir / cmd[0]), *args, "--print-config"], capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 0, r.stderr
        assert '"namespace"' in r.stdout
    mounts = {v.split(":")[0] for s in services.values() for v in s.get("volumes", []) if v.startswith("./")}
    for m in mounts:
        assert (ROOT / m).exists(), m


def test_image_recipe_installs_the_project():
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^RUN pip install \.", text, re.M)
    for src in ("pyproject.toml", "shared", "services"):
        assert src in text
    assert "<2.14" in text


def test_compose_health_checks_and_start_order():
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    for name, svc in services.items():
        assert svc.get("healthcheck", {}).get("test"), f"{name} has no health check"
    for name in ("query", "mapper", "frontend"):
        test = services[name]["healthcheck"]["test"]
        if test[0] == "CMD-SHELL":
            assert re.search(rf"(^|&& )aisdf-health {name} ", test[1]), test
        else:
            assert test[:3] == ["CMD", "aisdf-health", name]
        assert services[name]["depends_on"]["zenoh"] == {"condition": "service_healthy"}
    assert services["frontend"]["depends_on"]["mapper"] == {"condition": "service_healthy"}
    # query replicas (--scale query=2, host networking: one host name): each checks its own token,
    # the id its command picked and wrote down, not any replica's
    q = services["query"]
    assert "/tmp/aisdf-replica-id" in q["command"][2] and '--replica-id "$$id"' in q["command"][2]
    assert '--id "$$(cat /tmp/aisdf-replica-id)"' in q["healthcheck"]["test"][1]
    # mapper slots (--scale mapper=3): each checks the exact id of the slot its process holds
    # (a prefix would let mapper-1 take mapper-10's token for its own)
    assert "--id mapper-" in services["mapper"]["healthcheck"]["test"][1]


def test_overrides_keep_traffic_on_the_host_network():
    host = yaml.safe_load((ROOT / "deploy/compose.host.yml").read_text())["services"]
    base = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    assert set(host) == set(base) and all(s["network_mode"] == "host" for s in host.values())
    tls = yaml.safe_load((ROOT / "deploy/tls/compose.tls.yml").read_text())["services"]
    for name in ("query", "mapper", "frontend"):  # each service gets its own key only
        keys = [v for v in tls[name]["volumes"] if v.endswith(".key:ro") or ".key:" in v]
        assert keys == [f"./deploy/tls/certs/{name}.key:/etc/aisdf/tls/{name}.key:ro"]
    for text in [(ROOT / f).read_text() for f in ("docker-compose.yml", "deploy/compose.host.yml",
                                                   "deploy/tls/compose.tls.yml")]:
        assert "networks:" not in text


def test_build_context_leaves_out_local_state():
    ignored = (ROOT / ".dockerignore").read_text().split()
    for path in (".git/", ".venv/", "runs/", "results/", "tests/"):
        assert path in ignored


def test_services_need_no_benchmark_or_viewer_dependencies():
    deps = " ".join(PYPROJECT["project"]["dependencies"])
    for heavy in ("rerun", "open3d", "matplotlib", "pyarrow", "opencv"):
        assert heavy not in deps
    extras = PYPROJECT["project"]["optional-dependencies"]
    assert "rerun-sdk" in " ".join(extras["viewer"]) and "open3d" in " ".join(extras["bench"])
    assert "aisdf[bench,viewer]" in extras["dev"]
