"""Zenoh's own security, with the files of deploy/zenoh/secure on a real router process on loopback.

`make certs` issues the CA, the router's certificate and every identity's certificate and password into a
temporary directory; the router runs the committed router.json5 (TLS only, mutual TLS, user/password, the
generated ACL) with its certificate paths pointed there; the service and the clients use the committed
client configurations the same way. Then:

* an authorised vehicle publishes and gets its estimates back from the real service, and a simulated fleet
  runs end to end, each only with its own keys;
* a client without a certificate, with a wrong password, or over plain TCP gets no session at all;
* an authorised vehicle cannot publish another vehicle's measurements, declare its liveliness token or put
  estimates, and receives no other vehicle's estimates: the same attempts against an open router (the plain
  configuration) succeed, so these tests fail without the ACL.

Negative outcomes are decided by order, not by waiting: each forgery is followed, on the same session, by a
legitimate message, and the witnesses wait (bounded) for that one; whatever the router let through before
it has arrived by then.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh

from agv_protocol.wire import Estimate, ownership_key, ownership_selector, vehicle_key
from agv_protocol.zenoh_session import TransportError
from edge_client.transport import TransportOptions, close_session, open_session
from service.zenoh_acl import read_vehicle_list, render_json5, router_config
from tests.service.helpers import (
    PERIOD_NS,
    T0_NS,
    ServiceProcess,
    free_port,
    make_settings,
    plant_measurements,
    wait_for,
)

ROOT = Path(__file__).resolve().parents[2]
SECURE = ROOT / "deploy" / "zenoh" / "secure"
CLIENT = SECURE / "client.json5"
PLAIN_ROUTER = ROOT / "deploy" / "zenoh" / "router.json5"
ROUTER_SCRIPT = ROOT / "tests" / "edge_client" / "zenoh_router.py"
#: Where the committed configurations expect the certificates (the docker compose mount).
MOUNT = "/etc/zenoh/certs"
#: A vehicle with its own identity, and one of the simulated fleet's (identity agv-fleet-sim).
VEHICLE, OTHER = "truck-7", "veh-000"
#: How long a refused client keeps trying before open fails [s].
REFUSED_TIMEOUT_S = 2.0


def localised(config: Path, certs: Path, dest: Path) -> Path:
    """``config`` with the compose mount point replaced by the directory ``certs``, written to ``dest``."""
    dest.write_text(config.read_text().replace(MOUNT, str(certs)))
    return dest


@dataclass
class Router:
    """A router process on 127.0.0.1 and how its clients are configured."""

    endpoint: str
    secure: bool
    certs: Path | None = None
    workdir: Path | None = None

    def options(self, identity: str, **overrides: Any) -> TransportOptions:
        """Transport options of a client: as ``identity`` (client.json5, its certificate and credentials) on
        the secure router, plain on the open one."""
        base: dict[str, Any] = {"connect": (self.endpoint,), "connect_timeout_s": 10.0}
        if self.secure:
            assert self.certs is not None and self.workdir is not None
            base["config_file"] = localised(CLIENT, self.certs / identity, self.workdir / f"{identity}.json5")
            base["credentials_file"] = self.certs / identity / "credentials"
        base.update(overrides)
        return TransportOptions(**base)

    def session(self, identity: str) -> zenoh.Session:
        return open_session(self.options(identity))


def start_router(endpoint: str, config: Path) -> subprocess.Popen[str]:
    process = subprocess.Popen(
        [sys.executable, str(ROUTER_SCRIPT), endpoint, str(config)], stdout=subprocess.PIPE, text=True
    )
    assert process.stdout is not None
    line = process.stdout.readline().strip()
    if line != "ready":
        stop(process)
        raise AssertionError(f"the router on {endpoint} did not start ({line!r})")
    return process


def stop(process: subprocess.Popen[Any]) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=20)


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Everything `make certs` issues for the committed vehicle list, in a temporary directory."""
    out = tmp_path_factory.mktemp("secrets") / "zenoh"
    done = subprocess.run(
        ["make", "-C", str(ROOT), "certs", f"CERTS_DIR={out}"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return out


@pytest.fixture(scope="module")
def secure_router(certs: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Router]:
    workdir = tmp_path_factory.mktemp("secure-router")
    endpoint = f"tls/127.0.0.1:{free_port()}"  # the router's certificate names 127.0.0.1
    process = start_router(endpoint, localised(SECURE / "router.json5", certs / "router", workdir / "router.json5"))
    try:
        yield Router(endpoint, secure=True, certs=certs, workdir=workdir)
    finally:
        stop(process)


@pytest.fixture(scope="module")
def open_router() -> Iterator[Router]:
    """The plain configuration (docker-compose.yml's router): no TLS, no authentication, no ACL."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    process = start_router(endpoint, PLAIN_ROUTER)
    try:
        yield Router(endpoint, secure=False)
    finally:
        stop(process)


@pytest.fixture(params=["secure", "open"])
def router(request: pytest.FixtureRequest) -> Router:
    return request.getfixturevalue(f"{request.param}_router")  # type: ignore[no-any-return]


def test_the_committed_router_config_is_the_generated_one_and_zenoh_reads_every_file():
    """router.json5 is what `agv-fe zenoh-acl` makes of vehicles.txt (regenerate: make zenoh-acl), and
    Zenoh 1.x accepts each file's keys (it refuses unknown ones)."""
    from agv_fe.commands.zenoh_acl import HEADER

    vehicles = "deploy/zenoh/secure/vehicles.txt"
    grants = read_vehicle_list((ROOT / vehicles).read_text(), vehicles)
    header = [line.format(vehicles=vehicles, output="deploy/zenoh/secure/router.json5") for line in HEADER]
    assert (SECURE / "router.json5").read_text() == render_json5(router_config(grants), header)
    for path in sorted(SECURE.glob("*.json5")):
        zenoh.Config.from_file(str(path))
    assert {(g.vehicle_id, g.identity) for g in grants} >= {(VEHICLE, VEHICLE), (OTHER, "agv-fleet-sim")}


def test_make_certs_issues_one_directory_per_identity_and_the_router_dictionary(certs: Path):
    identities = {"agv-service", "agv-dashboard", "agv-fleet-sim", VEHICLE}
    assert {p.name for p in certs.iterdir()} == identities | {"ca", "router"}
    users = dict(line.split(":", 1) for line in (certs / "router" / "users.txt").read_text().splitlines())
    assert set(users) == identities
    for identity in identities:
        assert f"{identity}:{users[identity]}" == (certs / identity / "credentials").read_text().strip()
        subject = subprocess.run(
            ["openssl", "x509", "-in", str(certs / identity / "cert.pem"), "-noout", "-subject"],
            capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
        assert subject.strip().replace(" ", "") == f"subject=CN={identity}"
        assert (certs / identity / "key.pem").stat().st_mode & 0o077 == 0  # the key is its owner's only
    # run again: nothing is issued anew, passwords stay
    again = subprocess.run(["make", "-C", str(ROOT), "certs", f"CERTS_DIR={certs}"], capture_output=True, text=True)
    assert again.returncode == 0 and "issued" not in again.stdout, again.stdout


@pytest.mark.parametrize(
    "refused",
    ["no client certificate", "wrong password", "no password", "plain tcp", "certificate of another CA"],
)
def test_a_client_without_valid_credentials_gets_no_session(secure_router: Router, tmp_path: Path, refused: str):
    certs = secure_router.certs
    assert certs is not None
    good = secure_router.options(VEHICLE)
    assert good.config_file is not None
    text = good.config_file.read_text()
    config, credentials = tmp_path / "client.json5", tmp_path / "credentials"
    credentials.write_text((certs / VEHICLE / "credentials").read_text())
    endpoint = secure_router.endpoint
    if refused == "no client certificate":
        text = "\n".join(line for line in text.splitlines() if "connect_" not in line and "enable_mtls" not in line)
    elif refused == "wrong password":
        credentials.write_text(f"{VEHICLE}:not-the-password\n")
    elif refused == "plain tcp":
        endpoint = endpoint.replace("tls/", "tcp/")
    elif refused == "certificate of another CA":  # the right name, issued by a CA the router does not trust
        other = tmp_path / "other-ca"
        subprocess.run([str(ROOT / "deploy/zenoh/make-certs.sh"), str(other), VEHICLE], capture_output=True, check=True)
        for name in ("cert.pem", "key.pem"):
            text = text.replace(f"{certs}/{VEHICLE}/{name}", f"{other}/{VEHICLE}/{name}")
    config.write_text(text)
    options = TransportOptions(
        connect=(endpoint,),
        connect_timeout_s=REFUSED_TIMEOUT_S,
        config_file=None if refused == "plain tcp" else config,
        credentials_file=None if refused in ("no password", "plain tcp") else credentials,
    )
    try:
        close_session(open_session(options))
    except TransportError:
        pass
    else:
        pytest.fail(f"the router let in a client with {refused}")
    # the same client with its own credentials is let in
    close_session(open_session(good))


@dataclass
class Witness:
    """What a session received: samples by key, and liveliness tokens seen appearing."""

    samples: list[tuple[str, bytes]] = field(default_factory=list)
    tokens: list[str] = field(default_factory=list)

    def on_sample(self, sample: zenoh.Sample) -> None:
        self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.tokens.append(str(sample.key_expr))

    def has(self, key: str, payload: bytes | None = None) -> bool:
        return any(k == key and (payload is None or p == payload) for k, p in self.samples)


def test_a_vehicle_cannot_publish_as_another_nor_put_estimates_nor_read_others(router: Router):
    """Vehicle truck-7 (authorised, own certificate and password) forges veh-000's measurement, payload report
    and liveliness token and puts estimates; veh-000 (the fleet simulator's identity) subscribes to every
    estimate. On the secure router nothing forged arrives and veh-000 gets only its own estimates; on the
    open router all of it arrives, which shows these assertions can fail."""
    key = {
        (vid, kind): vehicle_key(vid, kind)  # type: ignore[arg-type]
        for vid in (VEHICLE, OTHER)
        for kind in ("meas", "alive", "estimate", "payload")
    }
    sessions: list[zenoh.Session] = []
    entities: list[Any] = []

    def session(identity: str) -> zenoh.Session:
        sessions.append(router.session(identity))
        return sessions[-1]

    def declare(entity: Any) -> Any:
        entities.append(entity)
        return entity

    try:
        service, monitor = Witness(), Witness()
        as_service = session("agv-service")  # sees what the service would
        declare(as_service.declare_subscriber("agv/v1/*/*/meas", service.on_sample))
        declare(as_service.declare_subscriber("agv/v1/*/*/payload", service.on_sample))
        declare(as_service.liveliness().declare_subscriber("agv/v1/*/*/alive", service.on_token, history=True))
        as_monitor = session("agv-dashboard")
        declare(as_monitor.declare_subscriber("agv/v1/*/*/estimate", monitor.on_sample))
        fleet = Witness()
        as_fleet = session("agv-fleet-sim")  # subscribes as edge_client's publisher does
        declare(as_fleet.declare_subscriber("agv/v1/*/*/estimate", fleet.on_sample))

        vehicle = session(VEHICLE)
        own_meas = declare(vehicle.declare_publisher(key[VEHICLE, "meas"]))
        forged_meas = declare(vehicle.declare_publisher(key[OTHER, "meas"]))
        own_payload = declare(vehicle.declare_publisher(key[VEHICLE, "payload"]))
        forged_payload = declare(vehicle.declare_publisher(key[OTHER, "payload"]))
        forged_estimates = [declare(vehicle.declare_publisher(key[v, "estimate"])) for v in (VEHICLE, OTHER)]
        service_estimates = [declare(as_service.declare_publisher(key[v, "estimate"])) for v in (VEHICLE, OTHER)]
        wait_for(lambda: own_meas.matching_status.matching, what="the vehicle to see the service's subscriber")
        wait_for(lambda: own_payload.matching_status.matching, what="the vehicle to see the payload subscriber")
        wait_for(lambda: all(p.matching_status.matching for p in service_estimates), what="estimate subscribers")
        if not router.secure:  # an open router tells the vehicle of the estimate subscribers: it then sends
            wait_for(lambda: all(p.matching_status.matching for p in forged_estimates), what="forgery targets")

        # the forgeries, then on the same session the vehicle's own measurement and token
        forged_meas.put(b"forged")
        forged_payload.put(b"forged")
        declare(vehicle.liveliness().declare_token(key[OTHER, "alive"]))
        for publisher in forged_estimates:
            publisher.put(b"forged")
        own_meas.put(b"marker")
        own_payload.put(b"marker")
        declare(vehicle.liveliness().declare_token(key[VEHICLE, "alive"]))
        wait_for(lambda: service.has(key[VEHICLE, "meas"], b"marker"), what="the vehicle's own measurement")
        wait_for(lambda: service.has(key[VEHICLE, "payload"], b"marker"), what="the vehicle's own payload report")
        wait_for(lambda: key[VEHICLE, "alive"] in service.tokens, what="the vehicle's own liveliness token")
        # then the service answers both vehicles: causally after every forgery
        for publisher in service_estimates:
            publisher.put(b"answer")
        wait_for(lambda: all(monitor.has(key[v, "estimate"], b"answer") for v in (VEHICLE, OTHER)), what="answers")
        wait_for(lambda: fleet.has(key[OTHER, "estimate"], b"answer"), what="veh-000's answer")

        got = {
            "forged measurement": service.has(key[OTHER, "meas"]),
            "forged payload report": service.has(key[OTHER, "payload"]),
            "forged liveliness token": key[OTHER, "alive"] in service.tokens,
            "forged estimates": monitor.has(key[VEHICLE, "estimate"], b"forged")
            or monitor.has(key[OTHER, "estimate"], b"forged"),
            "another vehicle's estimate": fleet.has(key[VEHICLE, "estimate"]),
        }
        expected = dict.fromkeys(got, not router.secure)
        assert got == expected
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        for s in reversed(sessions):
            close_session(s)


def test_replicas_hear_each_others_ownership_announcements_and_a_vehicle_cannot_forge_one(router: Router):
    """Replica r2 (the service's identity) announces the buckets it took; replica r1 and the terminal dashboard
    hear it. Vehicle truck-7 forges an announcement for r2, then sends its own measurement on the same session,
    which r1 receives after the forgery if the router forwarded it: on the secure router the forgery never
    arrives; on the open router it does, which shows the assertion can fail."""
    sessions: list[zenoh.Session] = []
    entities: list[Any] = []
    key, own_meas = ownership_key("r2"), vehicle_key(VEHICLE, "meas")
    try:
        r1, monitor = Witness(), Witness()
        for identity, witness in (("agv-service", r1), ("agv-dashboard", monitor)):
            sessions.append(router.session(identity))
            entities.append(sessions[-1].declare_subscriber(ownership_selector(), witness.on_sample))
        entities.append(sessions[0].declare_subscriber(own_meas, r1.on_sample))
        sessions.append(router.session("agv-service"))
        announce = sessions[-1].declare_publisher(key)
        sessions.append(router.session(VEHICLE))
        forged, meas = sessions[-1].declare_publisher(key), sessions[-1].declare_publisher(own_meas)
        entities += [announce, forged, meas]
        wait_for(lambda: announce.matching_status.matching, what="the replicas' subscribers")
        wait_for(lambda: meas.matching_status.matching, what="the vehicle to see r1's subscriber")
        if not router.secure:
            wait_for(lambda: forged.matching_status.matching, what="the forgery's target")
        forged.put(b"forged")
        meas.put(b"marker")
        announce.put(b"announced")
        wait_for(lambda: r1.has(own_meas, b"marker"), what="the vehicle's own measurement")
        wait_for(lambda: r1.has(key, b"announced") and monitor.has(key, b"announced"), what="the announcement")
        assert r1.has(key, b"forged") == (not router.secure)
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        for s in reversed(sessions):
            close_session(s)


def serve_securely(router: Router, workdir: Path, **sections: Any) -> ServiceProcess:
    """`agv-fe serve` as a client of the secure router, with the committed service configuration (not started)."""
    certs = router.certs
    assert certs is not None
    config = localised(CLIENT, certs / "agv-service", workdir / "service.json5")
    zenoh_section = {
        "mode": "client",
        "endpoint": router.endpoint,
        "config_file": str(config),
        "credentials_file": str(certs / "agv-service" / "credentials"),
        **sections.pop("zenoh", {}),
    }
    return ServiceProcess(make_settings(workdir, zenoh=zenoh_section, **sections), workdir / "service.log")


@pytest.fixture(scope="module")
def secure_service(secure_router: Router, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """`agv-fe serve` as a client of the secure router, with the committed service configuration."""
    server = serve_securely(secure_router, tmp_path_factory.mktemp("secure-service"))
    try:
        server.start().wait_ready()
        yield server
    finally:
        server.close()


def test_an_authorised_vehicle_and_fleet_work_end_to_end(secure_router: Router, secure_service: ServiceProcess):
    """truck-7 publishes and receives all its estimates, subscribed to every vehicle's estimates as the edge
    client is; the simulated fleet (agv-fe fleet with the committed fleet-sim configuration) runs meanwhile
    with every sample answered; truck-7 never receives one of the fleet's estimates."""
    samples = plant_measurements([VEHICLE], 200)
    received: list[Estimate] = []

    def collect(sample: zenoh.Sample) -> None:
        received.append(Estimate.decode(sample.payload.to_bytes()))

    session = secure_router.session(VEHICLE)
    entities: list[Any] = []
    try:
        entities.append(session.declare_subscriber("agv/v1/*/*/estimate", collect))
        entities.append(session.liveliness().declare_token(vehicle_key(VEHICLE, "alive")))
        publisher = session.declare_publisher(
            vehicle_key(VEHICLE, "meas"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        entities.append(publisher)
        wait_for(lambda: publisher.matching_status.matching, what="the service's subscriber")

        def publish(rows: list[list[Any]]) -> Callable[[], bool]:
            for row in rows:
                publisher.put(row[0].encode())
            last = rows[-1][0].seq
            return lambda: any(e.seq == last for e in received)

        wait_for(publish(samples[:100]), what="truck-7's estimates")
        options = secure_router.options("agv-fleet-sim")
        fleet = subprocess.run(
            [
                sys.executable, "-m", "agv_fe", "fleet", "--vehicles", "2", "--duration", "2", "--truth-hz", "0",
                "--connect", secure_router.endpoint, "--zenoh-config", str(options.config_file),
                "--zenoh-credentials", str(options.credentials_file),
            ],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert fleet.returncode == 0, fleet.stdout + fleet.stderr
        assert "estimates 400" in " ".join(fleet.stdout.split()), fleet.stdout  # 2 vehicles x 200 samples
        # the service answered the fleet while truck-7 listened to every estimate key; its next answers
        # to truck-7 come after those
        wait_for(publish(samples[100:]), what="truck-7's later estimates")
        assert [e.vehicle for e in received] == [VEHICLE] * 200
        assert [e.seq for e in received] == list(range(200))
        detail = secure_service.get(f"/vehicles/{VEHICLE}").json()
        assert detail["counters"]["accepted"] == 200 and detail["alive"] is True
        assert secure_service.get("/vehicles/veh-001").json()["counters"]["accepted"] == 200
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        close_session(session)


def test_the_services_own_processes_read_its_fleet_stream_through_the_secure_router(
    secure_router: Router, tmp_path: Path
):
    """With the vehicle estimates and the history each in a process of its own (service/fleet_child.py), both
    clients of the secure router with the service's identity, which the ACL lets read the fleet stream: truck-7
    receives every estimate on its key from the one process, and the other keeps them for the REST history."""
    server = serve_securely(
        secure_router, tmp_path, zenoh={"vehicle_publisher": "process"}, history={"writer": "process"}
    )
    session = secure_router.session(VEHICLE)
    received: list[Estimate] = []
    entities: list[Any] = []
    try:
        server.start().wait_ready()
        entities.append(
            session.declare_subscriber(
                vehicle_key(VEHICLE, "estimate"), lambda s: received.append(Estimate.decode(s.payload.to_bytes()))
            )
        )
        publisher = session.declare_publisher(
            vehicle_key(VEHICLE, "meas"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        entities.append(publisher)
        wait_for(lambda: publisher.matching_status.matching, what="the service's subscriber")
        for row in plant_measurements([VEHICLE], 50):
            publisher.put(row[0].encode())
        wait_for(lambda: len(received) >= 50, what="truck-7's estimates from the vehicle-estimate process")
        assert [e.seq for e in received] == list(range(50))
        whole = {"start": T0_NS / 1e9, "end": (T0_NS + 50 * PERIOD_NS) / 1e9}
        wait_for(
            lambda: len(server.get(f"/vehicles/{VEHICLE}/estimates", params=whole).json()["estimates"]) == 50,
            what="the history process holding every estimate",
        )
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        close_session(session)
        server.close()


def test_the_config_file_must_agree_with_the_settings_and_credentials_are_user_and_password(tmp_path: Path):
    from service.transport import zenoh_config

    config = tmp_path / "client.json5"
    config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": ["tls/elsewhere:7447"]}}))
    with pytest.raises(TransportError, match="connect/endpoints"):
        zenoh_config("client", "tls/router:7447", config_file=config)
    zenoh_config("client", "tls/elsewhere:7447", config_file=config)  # the same value twice is fine
    credentials = tmp_path / "credentials"
    credentials.write_text("just-a-password\n")
    with pytest.raises(TransportError, match="USER:PASSWORD") as refused:
        zenoh_config("client", "tls/elsewhere:7447", config_file=config, credentials_file=credentials)
    assert "just-a-password" not in str(refused.value)
    credentials.write_text("truck-7:secret:with:colons\n")
    config.write_text(CLIENT.read_text())
    built = zenoh_config("client", "tls/router:7447", config_file=config, credentials_file=credentials)
    assert json.loads(built.get_json("transport/auth/usrpwd/user")) == "truck-7"
    assert json.loads(built.get_json("transport/auth/usrpwd/password")) == "secret:with:colons"
    assert json.loads(built.get_json("scouting/multicast/enabled")) is False
    assert json.loads(built.get_json("connect/endpoints")) == ["tls/router:7447"]
