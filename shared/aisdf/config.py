"""Typed configuration: defaults in code, then a file, then environment variables, then
the command line (each later source overrides the earlier ones).

* File: YAML or JSON, the same nesting as the model (``--config FILE``).
* Environment: ``AISDF_<FIELD>`` with ``__`` between nested fields, e.g.
  ``AISDF_NAMESPACE=aisdf/robot2``, ``AISDF_ZENOH__CONNECT='["tcp/10.0.0.2:7447"]'``,
  ``AISDF_TRAINING__PRESET=cpu``. Values are parsed as JSON when they parse, else taken
  as strings. Variables naming fields a service does not have are ignored by it.
* Command line: the flags each service documents, and ``--set a.b=value`` for any field.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any, Literal, Mapping, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator

from . import __version__
from .keys import DEFAULT_NAMESPACE, validate_namespace

ENV_PREFIX = "AISDF_"


class Model(BaseModel):
    """Base for every config model: unknown keys are errors, assignments are checked."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ZenohOptions(Model):
    """Zenoh transport settings (protocol.md, "Transport")."""

    config_file: Path | None = Field(None, description="Zenoh JSON5 configuration file, applied first")
    mode: Literal["peer", "client", "router"] | None = Field(None, description="Zenoh mode; default peer")
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.2:7447")
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on, e.g. tcp/127.0.0.1:7447")
    multicast_scouting: bool | None = Field(None, description="multicast scouting; None keeps Zenoh's default (on)")


class ServiceConfig(Model):
    """Settings every service shares."""

    namespace: str = Field(DEFAULT_NAMESPACE, description="key prefix of every key, e.g. aisdf/robot2")
    zenoh: ZenohOptions = Field(default_factory=ZenohOptions)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"

    @field_validator("namespace")
    @classmethod
    def _ns(cls, v: str) -> str:
        return validate_namespace(v)


C = TypeVar("C", bound=BaseModel)


def deep_merge(base: dict, over: Mapping) -> dict:
    """Recursively merge ``over`` into a copy of ``base``."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(dict(out[k]), v)
        else:
            out[k] = v
    return out


def set_path(d: dict, dotted: str, value: Any) -> dict:
    """Set ``d["a"]["b"] = value`` for ``dotted = "a.b"``, creating maps on the way."""
    parts = [p for p in dotted.split(".") if p]
    if not parts:
        raise ValueError("empty key")
    cur = d
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
        if not isinstance(cur, dict):
            raise ValueError(f"{dotted}: {p} is not a section")
    cur[parts[-1]] = value
    return d


def parse_value(text: str) -> Any:
    """JSON when it parses (numbers, booleans, lists, null), else the string itself."""
    try:
        return json.loads(text)
    except (json.JSONDecodeError, ValueError):
        return text


def _field_names(model: type[BaseModel]) -> dict[str, Any]:
    return dict(model.model_fields)


def env_overrides(model: type[BaseModel], environ: Mapping[str, str] | None = None) -> dict:
    """Overrides from ``AISDF_*`` variables that name fields of ``model``."""
    environ = os.environ if environ is None else environ
    out: dict = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX) or name in ("AISDF_DATA",):
            continue
        path = name[len(ENV_PREFIX):].lower().split("__")
        if len(path) == 1 and path[0] in getattr(model, "LEGACY_KEYS", ()):  # read by the model's own validator
            out[path[0]] = parse_value(raw)
            continue
        # Only paths that exist in the model.
        cur: Any = model
        ok = True
        for p in path:
            fields = _field_names(cur) if isinstance(cur, type) and issubclass(cur, BaseModel) else {}
            if p not in fields:
                ok = False
                break
            ann = fields[p].annotation
            cur = ann if isinstance(ann, type) else None
        if ok:
            set_path(out, ".".join(path), parse_value(raw))
    return out


def load_file(path: str | Path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    data = yaml.safe_load(p.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"config file {p} must hold a map at the top level")
    return data


def build_config(
    model: type[C],
    file: str | Path | None = None,
    overrides: Mapping | None = None,
    environ: Mapping[str, str] | None = None,
    base: Mapping | None = None,
) -> C:
    """Resolve a config: defaults (or ``base``) < file < environment < overrides."""
    data: dict = dict(base or {})
    if file:
        data = deep_merge(data, load_file(file))
    data = deep_merge(data, env_overrides(model, environ))
    if overrides:
        data = deep_merge(data, overrides)
    return model.model_validate(data)


# ----------------------------------------------------------------------------- command line


def add_common_args(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Flags every service shares: config file, namespace, Zenoh transport, overrides."""
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("--config", metavar="FILE", help="YAML/JSON config file (same nesting as the config model)")
    parser.add_argument("--namespace", help=f"key prefix (default {DEFAULT_NAMESPACE}; env AISDF_NAMESPACE)")
    z = parser.add_argument_group("Zenoh transport")
    z.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file")
    z.add_argument("--mode", choices=["peer", "client", "router"], help="Zenoh mode (default peer)")
    z.add_argument("--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)")
    z.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    z.add_argument("--no-multicast-scouting", action="store_true", help="disable multicast scouting")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="override any config field, e.g. --set training.preset=cpu (repeatable)",
    )
    parser.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    parser.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    return parser


def overrides_from_args(args: argparse.Namespace, extra: Mapping[str, Any] | None = None) -> dict:
    """Turn the common flags (and ``extra`` dotted keys, None skipped) into overrides."""
    out: dict = {}
    if args.namespace:
        set_path(out, "namespace", args.namespace)
    if args.zenoh_config:
        set_path(out, "zenoh.config_file", args.zenoh_config)
    if args.mode:
        set_path(out, "zenoh.mode", args.mode)
    if args.connect:
        set_path(out, "zenoh.connect", list(args.connect))
    if args.listen:
        set_path(out, "zenoh.listen", list(args.listen))
    if args.no_multicast_scouting:
        set_path(out, "zenoh.multicast_scouting", False)
    if args.log_level:
        set_path(out, "log_level", args.log_level)
    for k, v in (extra or {}).items():
        if v is not None:
            set_path(out, k, v)
    for item in args.set:
        if "=" not in item:
            raise SystemExit(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        set_path(out, k.strip(), parse_value(v))
    return out


PARENT_ENV = "AISDF_PARENT_PID"


def service_setup(cfg: ServiceConfig, name: str):
    """Logging for a service process and its stop event (``stop_event``)."""
    import logging

    from .memory import cap_arenas

    logging.basicConfig(level=cfg.log_level, format=f"%(asctime)s {name} %(levelname)s %(message)s")
    cap_arenas(2)  # a long-running process: freed memory is not kept in an arena per thread
    return stop_event(name)


def stop_event(name: str):
    """A stop event set by SIGINT/SIGTERM, or, when the process was started by
    ``aisdf.stack.Stack`` (``AISDF_PARENT_PID`` set), by its parent's death: a demo or a test
    run killed outright (SIGKILL, a CI time limit) leaves no service behind holding its ports
    and cores."""
    import logging
    import os
    import signal
    import threading

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    parent = os.environ.pop(PARENT_ENV, "")  # for this process only, not for any it starts
    if parent.isdigit():
        def watch(pid: int = int(parent), period: float = 1.0) -> None:
            # a process whose parent died is re-parented (to init or a subreaper): its parent id changes
            while not stop.wait(period):
                if os.getppid() != pid:
                    logging.getLogger(name).warning("parent process %d is gone: stopping", pid)
                    stop.set()
        threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    return stop


def config_from_args(model: type[C], args: argparse.Namespace, extra: Mapping[str, Any] | None = None) -> C:
    """Resolve a service config from parsed arguments; exits with a clear message if invalid."""
    from pydantic import ValidationError

    try:
        cfg = build_config(model, args.config, overrides_from_args(args, extra))
    except (ValidationError, FileNotFoundError, ValueError) as e:
        raise SystemExit(f"invalid configuration: {e}") from None
    if getattr(args, "print_config", False):
        print(cfg.model_dump_json(indent=2))
        raise SystemExit(0)
    return cfg
