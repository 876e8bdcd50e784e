"""Typed configuration: defaults < file < environment < command line."""

import argparse

import pytest
from pydantic import ValidationError

from aisdf.config import ServiceConfig, add_common_args, build_config, config_from_args, env_overrides
from aisdf_mapper.config import MapperConfig
from aisdf_query.config import QueryConfig


def parse(args):
    return add_common_args(argparse.ArgumentParser()).parse_args(args)


def test_defaults():
    c = QueryConfig()
    assert c.namespace == "aisdf" and c.zenoh.mode is None and c.zenoh.connect == [] and c.max_points == 1_000_000


def test_precedence(tmp_path):
    f = tmp_path / "q.yaml"
    f.write_text("namespace: aisdf/file\nmax_points: 10\nzenoh:\n  mode: client\n")
    env = {"AISDF_NAMESPACE": "aisdf/env", "AISDF_ZENOH__CONNECT": '["tcp/127.0.0.1:7000"]', "AISDF_CHUNK_POINTS": "7"}
    c = build_config(QueryConfig, f, environ=env)
    assert (c.namespace, c.max_points, c.zenoh.mode, c.zenoh.connect, c.chunk_points) == (
        "aisdf/env", 10, "client", ["tcp/127.0.0.1:7000"], 7)
    c = build_config(QueryConfig, f, {"namespace": "aisdf/cli", "max_points": 3}, environ=env)
    assert (c.namespace, c.max_points) == ("aisdf/cli", 3)


def test_env_ignores_other_services_fields():
    assert env_overrides(QueryConfig, {"AISDF_PRESET": "cpu", "AISDF_DATA": "/x"}) == {}
    assert env_overrides(MapperConfig, {"AISDF_PRESET": "cpu"}) == {"preset": "cpu"}


def test_cli_flags_and_set():
    a = parse(["--namespace", "aisdf/r2", "--mode", "peer", "--connect", "tcp/1.2.3.4:7447", "--connect",
               "tcp/1.2.3.5:7447", "--listen", "tcp/127.0.0.1:7448", "--no-multicast-scouting",
               "--set", "max_points=5", "--set", "zenoh.mode=client"])
    c = config_from_args(QueryConfig, a)
    assert c.namespace == "aisdf/r2" and c.zenoh.connect == ["tcp/1.2.3.4:7447", "tcp/1.2.3.5:7447"]
    assert c.zenoh.listen == ["tcp/127.0.0.1:7448"] and c.zenoh.multicast_scouting is False
    assert c.max_points == 5 and c.zenoh.mode == "client"  # --set comes last


@pytest.mark.parametrize("bad", [{"max_points": 0}, {"namespace": "a/*"}, {"unknown": 1}, {"zenoh": {"mode": "x"}},
                                 {"namespace": ""}])
def test_invalid_values_are_errors(bad):
    with pytest.raises(ValidationError):
        build_config(QueryConfig, overrides=bad, environ={})


def test_invalid_cli_exits_with_message():
    with pytest.raises(SystemExit) as e:
        config_from_args(ServiceConfig, parse(["--set", "namespace=a/**"]))
    assert "invalid configuration" in str(e.value)
    with pytest.raises(SystemExit):
        config_from_args(ServiceConfig, parse(["--config", "/nonexistent.yaml"]))


def test_the_mapper_choice_is_spelled_mapper_and_the_old_switch_still_reads(tmp_path):
    assert MapperConfig().mapper == "submaps"
    assert build_config(MapperConfig, overrides={"mapper": "single"}, environ={}).mapper == "single"
    f = tmp_path / "mapper.yaml"
    f.write_text("submaps: false\n")  # a file written before 'mapper'
    assert build_config(MapperConfig, f, environ={}).mapper == "single"
    assert build_config(MapperConfig, environ={"AISDF_SUBMAPS": "false"}).mapper == "single"
    assert build_config(MapperConfig, environ={"AISDF_SUBMAPS": "true"}).mapper == "submaps"
    assert build_config(MapperConfig, environ={"AISDF_SUBMAPS": "false", "AISDF_MAPPER": "submaps"}).mapper == "submaps"
    assert "submaps" not in env_overrides(QueryConfig, {"AISDF_SUBMAPS": "false"})  # the mapper's only
    with pytest.raises(ValidationError):
        MapperConfig(mapper="octree")
