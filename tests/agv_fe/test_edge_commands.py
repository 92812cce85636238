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


def test_publish_csv_names_the_bad_line_before_connecting(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vx,r,torque,steer\n0.00,10,0,100,0\n0.01,10,0,oops,0\n")
    out = agv_fe("publish-csv", str(bad), "--vehicle", "v1", "--connect", "tcp/127.0.0.1:9")
    assert out.returncode == 2
    assert "line 3" in out.stderr and "torque" in out.stderr


def test_publish_csv_rejects_a_bad_vehicle_id(tmp_path):
    out = agv_fe("publish-csv", str(tmp_path / "x.csv"), "--vehicle", "bad/id")
    assert out.returncode == 2 and "--vehicle" in out.stderr and "bad/id" in out.stderr


def test_dashboard_rejects_a_bad_refresh_rate():
    out = agv_fe("dashboard", "--refresh", "0.1")
    assert out.returncode == 2 and "--refresh" in out.stderr
