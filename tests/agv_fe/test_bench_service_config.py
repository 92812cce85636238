import json
import os
from pathlib import Path

import pytest

from agv_fe.benchmarks import secure_link, service_load
from agv_fe.benchmarks import service_config as bench
from agv_fe.benchmarks.harness import free_port, wait_for
from agv_protocol.wire import N_BUCKETS, fleet_selector, vehicle_key
from agv_protocol.zenoh_session import TransportError
from service.affinity import format_cpu_list
from service.transport import open_session
from service.zenoh_acl import VehicleGrant, access_control

pytestmark = pytest.mark.network


def test_the_configurations_alternate_and_each_service_runs_with_its_settings(tmp_path, monkeypatch):
    """Two rounds of history on and off against real `agv-fe serve` processes, 10 vehicles, short steps: the runs
    alternate ABBA (neither is always the one that follows the other's run), the history runs exactly in the
    services told to run it, nothing is lost, and the report's summary is computed from the runs it lists.
    Latencies are the machine's figures, not asserted."""
    monkeypatch.setattr(service_load, "STEP_S", 2.0)
    monkeypatch.setattr(service_load, "WARMUP_S", 0.5)
    runs = bench.measure(bench.HISTORY, rounds=2, vehicles=10, hold_s=3.0)
    assert [(r["round"], r["configuration"]) for r in runs] == [
        (1, "history on (default)"),
        (1, "history off"),
        (2, "history off"),
        (2, "history on (default)"),
    ]
    assert [r["history"] for r in runs] == [True, False, False, True]
    for r in runs:
        assert r["hold"]["vehicles"] == 10 and r["hold"]["zero_loss"]
        assert r["hold"]["estimates_received"] == r["hold"]["sent"] > 0
        # each process's wait for a core, counted by this Linux kernel (the run table shows it beside the CPU)
        assert all(r["hold"][f"{who}_waited"] >= 0 for who in ("service", "generator", "receiver"))
        # the service's event loop and Zenoh's threads ran, each a part of the service's CPU
        parts = [r["hold"][f"{group}_cpu"] for group in bench.THREAD_GROUPS]
        assert all(p > 0 for p in parts) and sum(parts) <= r["hold"]["service_cpu"] + 0.05
    text = bench.render("t", bench.HISTORY, runs, 10, "cmd")
    for r in runs:
        h = r["hold"]
        split = f"{h['event_loop_cpu']:.2f} / {h['zenoh_cpu']:.2f}"
        assert f"| {h['service_cpu']:.2f} | {split} | {bench._waits(h)} |" in text
    assert json.loads(text.rsplit("```json\n", 1)[1].split("\n```")[0]) == runs
    on, off = (bench._summary(c.label, runs) for c in bench.HISTORY)
    assert on["runs"] == off["runs"] == 2
    ratio = off["p99_median_ms"] / on["p99_median_ms"]
    assert f"| history off | 2 | {'yes' if off['clean'] else '**no**'} | {off['p99_median_ms']:.2f} / " in text
    assert f"| {ratio:.2f} |" in text and "`cmd` this one" in text


def test_a_baseline_that_is_not_a_checkout_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--baseline", str(tmp_path), "old", "--out", str(tmp_path / "r.md")])
    assert exc.value.code == 2
    assert "is not a checkout of this project" in capsys.readouterr().err


def test_a_setting_that_is_not_the_services_is_refused(tmp_path, capsys):
    (tmp_path / "agv_fe").mkdir()
    with pytest.raises(SystemExit) as exc:
        bench.main(["--baseline", str(tmp_path), "old", "--out", str(tmp_path / "r.md"), "--env", "PATH=/x"])
    assert exc.value.code == 2
    assert "--env takes AGV_FE_NAME=VALUE, got PATH=/x" in capsys.readouterr().err


def test_the_secure_configurations_carry_every_estimate_over_tls_only(monkeypatch):
    """TLS with the history off, with it on, with PostgreSQL bucket leases too, and with the history in its own
    process (a child of the embedded router on its Unix socket, let in by the router's user dictionary and
    ACL), one round each against real
    `agv-fe serve` processes (the service the TLS router, generator and receiver its clients with their
    certificates), 10 vehicles, short steps: every sample accepted and every estimate received over TLS, a plain TCP
    client refused at each service's endpoint, the ACL generated for the fleet in force, and the history and the
    leases running exactly where told. Latencies are the machine's figures, not asserted."""
    monkeypatch.setattr(service_load, "STEP_S", 2.0)
    monkeypatch.setattr(service_load, "WARMUP_S", 0.5)
    names = ("tls", "tls-history", "tls-history-leases", "tls-history-process")
    configs = tuple(bench.CONFIGURATIONS[n] for n in names)
    runs = bench.measure(configs, rounds=1, vehicles=10, hold_s=3.0)
    assert [r["configuration"] for r in runs] == [c.label for c in configs]
    for r in runs:
        for step in (r["warm"], r["hold"]):
            assert step["zero_loss"] and step["estimates_received"] == step["sent"] > 0
        assert r["endpoint"].startswith("tls/127.0.0.1:") and r["plain_tcp_refused"]
        assert r["acl_rules"] == len(access_control([])["rules"]) + 3 * 10  # three rules of its own per vehicle
    assert [r["history"] for r in runs] == [False, True, True, True]
    assert [r["leases"] for r in runs] == [False, False, True, False]
    assert runs[2]["buckets"] == N_BUCKETS
    text = bench.render("t", configs, runs, 10, "cmd")
    assert text.count(f"| TLS (plain TCP refused), ACL of {runs[0]['acl_rules']} rules |") == 4
    assert f"| PostgreSQL, leases, {N_BUCKETS} buckets |" in text and secure_link.FLEET_IDENTITY in text


def test_the_secure_link_admits_the_fleet_identity_for_its_vehicles_only(tmp_path):
    """The link of the TLS configurations on its own: a router session opened with the link's settings receives the
    fleet identity's measurements of a listed vehicle, not of an unlisted one (the ACL), and neither a plain TCP
    client nor a TLS client without credentials gets a session."""
    certs = secure_link.issue_certificates(tmp_path / "certs")
    link = secure_link.secure_link(certs, tmp_path, vehicles=3)
    assert link.acl_rules > 0 and link.env["AGV_FE_ZENOH__ENDPOINT"] == link.endpoint
    router = open_session("router", link.endpoint, config_file=link.env["AGV_FE_ZENOH__CONFIG_FILE"])
    try:
        got: list[str] = []
        sub = router.declare_subscriber(fleet_selector("meas"), lambda s: got.append(str(s.key_expr)))
        config, credentials = link.clients.generator
        fleet = open_session("client", link.endpoint, 5000, config_file=config, credentials_file=credentials)
        try:
            listed, unlisted = service_load.vehicle_ids(3)[2], "bench-99999"
            fleet.put(vehicle_key(unlisted, "meas"), b"forged")
            fleet.put(vehicle_key(listed, "meas"), b"listed")  # after the forgery, on the same session
            wait_for(lambda: vehicle_key(listed, "meas") in got, 10.0, "the listed vehicle's measurement")
            assert vehicle_key(unlisted, "meas") not in got
        finally:
            fleet.close()
        assert secure_link.plain_tcp_refused(link.endpoint)
        with pytest.raises(TransportError):
            open_session("client", link.endpoint, 1500, config_file=config).close()  # no password
        sub.undeclare()
    finally:
        router.close()


def test_the_plain_tcp_probe_finds_a_plain_listener():
    """The probe the TLS runs record can fail: at a plain TCP router's port it gets a session."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session("router", endpoint)
    try:
        assert not secure_link.plain_tcp_refused(endpoint.replace("tcp/", "tls/"))
    finally:
        router.close()


def test_a_baseline_compares_on_the_stream_and_link_asked_for_and_the_command_says_so(tmp_path):
    (tmp_path / "agv_fe").mkdir()
    parser = bench._parser()
    argv = ["--baseline", str(tmp_path), "old", "--label", "new", "--out", "r.md"]
    for options, stream, tls, said in (
        (["--stream", "vehicle-bin"], "vehicle-bin", False, " --stream vehicle-bin"),
        ([], "fleet", False, ""),
        (["--tls"], "fleet", True, " --tls"),
    ):
        args = parser.parse_args(argv + options)
        configs, title, which = bench._chosen(parser, args, {})
        assert [(c.label, c.source, c.stream, c.tls) for c in configs] == [
            ("old", tmp_path.resolve(), stream, tls),
            ("new", None, stream, tls),
        ]
        assert which == f"--baseline DIR 'old'{said} --label 'new'" and title == "Service capacity: old against new"


def test_the_command_in_the_report_names_every_option_not_at_its_default():
    parser = bench._parser()
    default = parser.parse_args(["--configs", "plain", "--out", "r.md"])
    assert (
        bench._command(default, "--configs plain")
        == "python -m agv_fe.benchmarks.service_config --configs plain --out r.md"
    )
    args = parser.parse_args(
        ["--configs", "plain", "--rounds", "3", "--vehicles", "1500", "--env", "AGV_FE_A=1", "--out", "r.md"]
    )
    assert bench._command(args, "--configs plain") == (
        "python -m agv_fe.benchmarks.service_config --configs plain --vehicles 1500 --rounds 3 --env AGV_FE_A=1"
        " --out r.md"
    )


def test_configs_names_the_configurations_and_excludes_a_baseline(tmp_path, capsys):
    out = str(tmp_path / "r.md")
    with pytest.raises(SystemExit) as exc:
        bench.main(["--configs", "plain,tls-fast", "--out", out])
    assert exc.value.code == 2
    assert "--configs takes names of plain, history-off, tls, tls-history" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        bench.main(["--configs", "plain", "--baseline", str(tmp_path), "old", "--out", out])
    assert exc.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err
    assert set(bench.EVERYTHING_ON) <= set(bench.CONFIGURATIONS)


def test_the_report_documents_how_to_run_everything_on_with_the_configurations_that_exist():
    """docs/benchmarks/service_config.md holds the section run() writes, and its command names configurations of
    :data:`CONFIGURATIONS` at the target's fleet; the ACL size it quotes is the generated one's."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "benchmarks" / "service_config.md").read_text()
    assert bench.EVERYTHING_ON_SECTION in text
    command = bench.EVERYTHING_ON_SECTION.split("```sh\n", 1)[1].split("```", 1)[0].replace("\\\n", " ").split()
    assert command[command.index("--configs") + 1] == ",".join(bench.EVERYTHING_ON)
    assert command[command.index("--vehicles") + 1] == "1500"
    fleet = [VehicleGrant(v, secure_link.FLEET_IDENTITY) for v in service_load.vehicle_ids(1500)]
    assert f"holds {len(access_control(fleet)['rules']):,}\nrules" in bench.EVERYTHING_ON_SECTION


def test_an_own_core_configuration_runs_the_service_on_its_cpu_and_the_harness_beside_it(monkeypatch):
    """The 'own core' runs: every thread of the service on the configuration's CPU, the benchmark (whose
    generator and receiver inherit its CPUs) on the others during the steps, and back on all of its own after."""
    allowed = os.sched_getaffinity(0)
    if str(min(allowed)) != bench.OWN_CORE:
        pytest.skip(f"CPU {bench.OWN_CORE} is not this process's")
    monkeypatch.setattr(service_load, "STEP_S", 2.0)
    monkeypatch.setattr(service_load, "WARMUP_S", 0.5)
    config = bench.CONFIGURATIONS["plain-own-core"]
    run = bench.measure_one(config, vehicles=10, hold_s=2.0)
    assert run["hold"]["zero_loss"] and run["hold"]["estimates_received"] == run["hold"]["sent"] > 0
    assert run["cpus"]["service"] == [bench.OWN_CORE]
    rest = allowed - {int(bench.OWN_CORE)} or allowed
    assert run["cpus"]["harness"] == format_cpu_list(rest)
    assert os.sched_getaffinity(0) == allowed
    assert "A core of its own" in bench.render("t", (config,), [{**run, "round": 1}], 10, "cmd")
