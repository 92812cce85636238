"""docker-compose.replicas.yml against the settings and the CLI (no Docker engine runs here): two replicas of one
PostgreSQL database behind the router, their environment real settings that select bucket leases, distinct
names, volumes and ports, health from /ready, and the database URL agreeing with the postgres service."""

from __future__ import annotations

from typing import Any

import yaml

from agv_fe.cli import build_parser
from service.settings import Settings
from tests.test_deployment import ROOT, _nested, interpolate, setting_field

COMPOSE = yaml.safe_load((ROOT / "docker-compose.replicas.yml").read_text())
SERVICES: dict[str, Any] = COMPOSE["services"]
REPLICAS = ("replica-a", "replica-b")
PLAIN = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]


def environment(name: str) -> dict[str, str]:
    return {k: interpolate(str(v)) for k, v in SERVICES[name]["environment"].items()}


def test_two_replicas_of_one_database_select_bucket_leases_with_distinct_names_and_volumes():
    assert set(SERVICES) == {"router", "postgres", "replica-a", "replica-b", "fleet"}
    assert SERVICES["router"] == PLAIN["router"]
    database = SERVICES["postgres"]["environment"]
    url = f"postgresql://{database['POSTGRES_USER']}:agv@postgres:5432/{database['POSTGRES_DB']}"
    names, volumes, ports = set(), set(), set()
    for name in REPLICAS:
        env = environment(name)
        for variable in env:
            setting_field(variable)  # KeyError if the variable sets nothing
        settings = Settings(**_nested(env))
        assert settings.bucket_leases and settings.database_url == url
        assert build_parser().parse_args(SERVICES[name]["command"]).command == "serve"
        names.add(settings.shard.replica_id)
        volumes.update(SERVICES[name]["volumes"])
        ports.update(SERVICES[name]["ports"])
        assert SERVICES[name]["depends_on"]["postgres"] == {"condition": "service_healthy"}
        assert "/ready" in " ".join(SERVICES[name]["healthcheck"]["test"])
    assert len(names) == len(volumes) == len(ports) == 2
    assert {v.split(":")[0] for v in volumes} | {"postgres-data"} == set(COMPOSE["volumes"])


def test_the_fleet_waits_for_both_replicas_and_parses_with_the_cli():
    fleet = SERVICES["fleet"]
    assert fleet["depends_on"] == {name: {"condition": "service_healthy"} for name in REPLICAS}
    args = build_parser().parse_args([interpolate(str(p)) for p in fleet["command"]])
    assert args.connect == [environment("replica-a")["AGV_FE_ZENOH__ENDPOINT"]]


def test_the_postgres_healthcheck_names_its_user_and_database():
    database = SERVICES["postgres"]
    test = database["healthcheck"]["test"]
    assert test[:2] == ["CMD", "pg_isready"]
    assert database["environment"]["POSTGRES_USER"] in test and database["environment"]["POSTGRES_DB"] in test
