"""The edge commands' argument handling, without a network."""

import subprocess
import sys

from agv_fe.commands import fleet as fleet_command
from edge_client.fleet_mix import DEFAULT_MIX, MIX_KINDS


def agv_fe(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "agv_fe", *args], capture_output=True, text=True, timeout=120)


def test_fleet_help_lists_the_same_kinds_and_default_as_the_mix_module():
    assert ", ".join(MIX_KINDS) == fleet_command.MIX_KINDS_HELP
    assert fleet_command.DEFAULT_MIX == DEFAULT_MIX


def test_fleet_rejects_a_bad_mix_naming_the_kind():
    out = agv_fe("fleet", "--vehicles", "2", "--duration", "1", "--scenario-mix", "healthy=1,torque_bais=1")
    assert out.returncode == 2
    assert "torque_bais" in out.stderr and "torque_bias" in out.stderr


def test_fleet_rejects_bad_numbers_and_modes():
    assert "--vehicles" in agv_fe("fleet", "--vehicles", "0").stderr
    assert "--duration" in agv_fe("fleet", "--duration", "nan").stderr
    out = agv_fe("fleet", "--mode", "peer", "--duration", "1")
    assert out.returncode == 2 and "--listen" in out.stderr


def test_fleet_reports_an_unreachable_router_with_its_endpoint():
    out = agv_fe(
        "fleet", "--vehicles", "1", "--duration", "1", "--connect", "tcp/127.0.0.1:9", "--connect-timeout", "0.5"
    )
    assert out.returncode == 2
    assert "tcp/127.0.0.1:9" in out.stderr and "cannot open a zenoh session" in out.stderr
