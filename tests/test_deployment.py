"""docker-compose.yml and the Dockerfile against the settings and the CLI.

No Docker engine runs here, so: the files are parsed and every command, port,
environment variable and endpoint in them is checked against what the code
accepts; then the compose topology runs as local processes (a router process
standing in for zenohd, the service and the fleet in client mode) with the
commands and environment taken from the compose file itself.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from packaging.requirements import Requirement

from agv_fe.cli import build_parser
from service.settings import Settings
from tests.edge_client.conftest import free_port

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
DOCKERFILE = (ROOT / "Dockerfile").read_text()
ROUTER_CONFIG = ROOT / "deploy" / "zenoh" / "router.json5"
SERVICES = COMPOSE["services"]


def interpolate(value: str, env: dict[str, str] | None = None) -> str:
    """Compose's ${VAR:-default} interpolation."""
    env = env or {}
    return re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: env.get(m.group(1), m.group(2)), value)


def command_of(name: str, env: dict[str, str] | None = None) -> list[str]:
    return [interpolate(str(part), env) for part in SERVICES[name]["command"]]


def environment_of(name: str) -> dict[str, str]:
    return {k: str(v) for k, v in SERVICES[name].get("environment", {}).items()}


def setting_field(variable: str) -> Any:
    """The Settings field an AGV_FE_* variable sets; KeyError when it names none."""
    path = variable.removeprefix("AGV_FE_").lower().split("__")
    model: Any = Settings
    field = None
    for part in path:
        field = model.model_fields[part]
        model = field.annotation
    return field


def dockerfile_env() -> dict[str, str]:
    """Every ENV of the Dockerfile (continued lines included), later stages overriding earlier ones."""
    env: dict[str, str] = {}
    for block in re.findall(r"^ENV (.*?)(?=^\S)", DOCKERFILE, re.S | re.M):
        env.update(re.findall(r"(\w+)=(\S+)", block))
    return env


def test_compose_runs_router_and_service_and_puts_the_demo_and_monitoring_behind_profiles():
    default = {name for name, spec in SERVICES.items() if "profiles" not in spec}
    assert default == {"router", "service"}  # production: no simulated vehicles
    for name in ("service", "fleet", "dashboard"):
        assert SERVICES[name]["image"] == "agv-fe:latest" and SERVICES[name]["build"] == "."
    # docker compose --profile demo adds the simulated fleet and the terminal dashboard; --profile monitoring adds
    # Prometheus and Grafana (tests/test_monitoring.py checks them)
    assert {name for name in SERVICES if name not in default} == {"fleet", "dashboard", "prometheus", "grafana"}
    assert all(SERVICES[name]["profiles"] == ["demo"] for name in ("fleet", "dashboard"))
    assert all(SERVICES[name]["profiles"] == ["monitoring"] for name in ("prometheus", "grafana"))
    assert COMPOSE["volumes"] == {"agv-data": None, "prometheus-data": None, "grafana-data": None}


def test_router_image_is_pinned_to_the_python_binding_and_its_config_is_mounted():
    router = SERVICES["router"]
    image, tag = router["image"].split(":")
    assert image == "eclipse/zenoh" and tag == metadata.version("eclipse-zenoh")
    mount = router["volumes"][0].split(":")
    assert (ROOT / mount[0]).resolve() == ROUTER_CONFIG and mount[2] == "ro"
    assert router["command"] == ["-c", mount[1]]
    config = ROUTER_CONFIG.read_text()
    listen_port = int(re.search(r'"tcp/0\.0\.0\.0:(\d+)"', config).group(1))
    assert router["ports"] == [f"{listen_port}:{listen_port}"]
    assert re.search(r"multicast:\s*\{\s*enabled:\s*false", config)


def test_service_environment_names_real_settings_and_agrees_with_ports_and_endpoints():
    env = environment_of("service")
    for variable in [*env, *dockerfile_env()]:
        if variable.startswith("AGV_FE_"):
            setting_field(variable)  # KeyError if the variable sets nothing
    settings = Settings(**_nested(env))  # the values validate
    assert settings.zenoh.mode == "client"
    host, port = settings.zenoh.endpoint.removeprefix("tcp/").split(":")
    assert host == "router" and f"{port}:{port}" in SERVICES["router"]["ports"]
    assert SERVICES["service"]["ports"] == [f"{settings.http.port}:{settings.http.port}"]
    assert str(settings.data_dir) == "/data" and "agv-data:/data" in SERVICES["service"]["volumes"]
    # the image agrees: same port and data dir, exposed, healthcheck on that port
    image_env = dockerfile_env()
    assert image_env["AGV_FE_HTTP__PORT"] == str(settings.http.port) and image_env["AGV_FE_DATA_DIR"] == "/data"
    assert re.search(rf"^EXPOSE .*\b{settings.http.port}\b", DOCKERFILE, re.M)
    assert "AGV_FE_HTTP__PORT" in DOCKERFILE.split("HEALTHCHECK", 1)[1] and "/health" in DOCKERFILE


def _nested(env: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for variable, value in env.items():
        *parents, leaf = variable.removeprefix("AGV_FE_").lower().split("__")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


@pytest.mark.parametrize("name", ["service", "fleet", "dashboard"])
def test_every_command_parses_with_the_cli(name):
    args = build_parser().parse_args(command_of(name))
    assert args.command == name if name != "service" else args.command == "serve"
    if name in ("fleet", "dashboard"):
        assert args.connect == [environment_of("service")["AGV_FE_ZENOH__ENDPOINT"]]
        assert args.connect_timeout == -1  # wait for the router, however long it takes to start


def test_start_order_is_health_based():
    assert SERVICES["service"]["depends_on"] == {"router": {"condition": "service_started"}}
    for name in ("fleet", "dashboard"):
        assert SERVICES[name]["depends_on"] == {"service": {"condition": "service_healthy"}}
        assert SERVICES[name]["healthcheck"] == {"disable": True}  # no HTTP in these roles
    # the service is healthy when /ready answers 200 on its own port: what depends on it waits for readiness
    check = SERVICES["service"]["healthcheck"]["test"]
    port = Settings(**_nested(environment_of("service"))).http.port
    assert check[:3] == ["CMD", "python", "-c"] and f"http://127.0.0.1:{port}/ready" in check[3]
    compile(check[3], "healthcheck", "exec")  # the command is valid Python
    assert int(command_of("fleet", {"FLEET_VEHICLES": "7"})[2]) == 7


def test_dockerfile_is_multi_stage_slim_non_root_and_pinned():
    stages = re.findall(r"^FROM (\S+)", DOCKERFILE, re.M)
    assert len(stages) == 2 and all(s.startswith("python:3.11-slim") for s in stages)
    user = re.findall(r"^USER (\S+)", DOCKERFILE, re.M)
    assert user == ["10001:10001"] and "useradd --system --uid 10001" in DOCKERFILE
    assert 'ENTRYPOINT ["agv-fe"]' in DOCKERFILE and 'CMD ["serve"]' in DOCKERFILE
    assert "pip install -r /tmp/requirements.lock" in DOCKERFILE and "pip install --no-deps ." in DOCKERFILE


def _pins(lock: str) -> dict[str, str]:
    pins = {}
    for line in (ROOT / lock).read_text().splitlines():
        if line and not line.startswith("#"):
            name, version = line.split("==")
            pins[name.lower().replace("_", "-")] = version
    return pins


def _declared(extras: tuple[str, ...] = ()) -> list[Requirement]:
    """pyproject's dependencies and those of ``extras``, the project's own extras (``[dev]`` names ``[can,ros2]``)
    expanded."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = [Requirement(r) for r in project["dependencies"]]
    pending = list(extras)
    while pending:
        for requirement in map(Requirement, project["optional-dependencies"][pending.pop()]):
            if requirement.name == project["name"]:
                pending.extend(requirement.extras)
            else:
                declared.append(requirement)
    return declared


@pytest.mark.parametrize(("lock", "extras"), [("requirements.lock", ()), ("requirements-dev.lock", ("dev",))])
def test_lock_pins_every_dependency_within_its_range(lock, extras):
    pins = _pins(lock)
    declared = _declared(extras)
    assert len(declared) > len(_declared()) or not extras  # the dev extras were expanded
    for requirement in declared:
        version = pins.get(requirement.name.lower().replace("_", "-"))
        assert version is not None, f"{requirement.name} is not pinned in {lock}"
        assert requirement.specifier.contains(version), f"{requirement.name}=={version} outside {requirement}"


def test_compose_topology_as_local_processes(tmp_path):
    """router (stand-in for zenohd, from the compose router config) + service + fleet, as compose runs them."""
    router_port, http_port = free_port(), free_port()
    local = {"router:7447": f"127.0.0.1:{router_port}"}

    def localise(parts: list[str]) -> list[str]:
        for old, new in local.items():
            parts = [p.replace(old, new) for p in parts]
        return parts

    router = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "edge_client" / "zenoh_router.py"), str(router_port), str(ROUTER_CONFIG)],
        stdout=subprocess.PIPE,
        text=True,
    )
    processes: list[subprocess.Popen[Any]] = [router]
    try:
        assert router.stdout is not None and router.stdout.readline().strip() == "ready"
        env = {**os.environ, **environment_of("service")}
        env.update(
            {
                "AGV_FE_ZENOH__ENDPOINT": localise([env["AGV_FE_ZENOH__ENDPOINT"]])[0],
                "AGV_FE_HTTP__HOST": "127.0.0.1",
                "AGV_FE_HTTP__PORT": str(http_port),
                "AGV_FE_DATA_DIR": str(tmp_path / "data"),
            }
        )
        log = (tmp_path / "service.log").open("w")
        service = subprocess.Popen(
            [sys.executable, "-m", "agv_fe", *command_of("service")], env=env, stdout=log, stderr=subprocess.STDOUT
        )
        processes.append(service)
        url = f"http://127.0.0.1:{http_port}"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            assert service.poll() is None, (tmp_path / "service.log").read_text()
            try:
                if httpx.get(f"{url}/ready", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.25)
        else:
            pytest.fail("the service never became ready")
        # the compose healthcheck's command, on this service's port: exit status 0 once it is ready
        probe_code = SERVICES["service"]["healthcheck"]["test"][3].replace(":8000/", f":{http_port}/")
        assert subprocess.run([sys.executable, "-c", probe_code], timeout=30).returncode == 0
        fleet_cmd = localise(command_of("fleet", {"FLEET_VEHICLES": "4", "FLEET_DURATION_S": "6"}))
        fleet = subprocess.run(
            [sys.executable, "-m", "agv_fe", *fleet_cmd], capture_output=True, text=True, timeout=120
        )
        assert fleet.returncode == 0, fleet.stderr
        assert "estimates 2400" in " ".join(fleet.stdout.split())  # 4 vehicles x 600 samples, all answered
        dashboard = subprocess.run(
            [sys.executable, "-m", "agv_fe", *localise(command_of("dashboard")), "--duration", "1"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert dashboard.returncode == 0, dashboard.stderr
        vehicles = httpx.get(f"{url}/vehicles", timeout=5).json()
        listed = vehicles["vehicles"] if isinstance(vehicles, dict) else vehicles
        assert len(listed) == 4
    finally:
        for process in reversed(processes):
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()


def test_the_image_builds_from_the_files_the_package_needs_and_runs_as_a_numeric_user():
    """pyproject names README.md and LICENSE (readme, license-files): the build stage copies both; the image's
    user is numeric (a runAsNonRoot policy checks it without /etc/passwd) and is the one owning /data."""
    copies = " ".join(line for line in DOCKERFILE.splitlines() if line.startswith("COPY pyproject.toml"))
    assert "README.md" in copies and "LICENSE" in copies
    users = [line.split()[1] for line in DOCKERFILE.splitlines() if line.startswith("USER ")]
    assert users and users[-1] == "10001:10001"
    assert "--uid 10001" in DOCKERFILE


def test_the_image_copies_every_package_pyproject_ships():
    """The build stage installs from the copied tree: a package pyproject ships but the Dockerfile does not copy
    (agv_protocol, say) would leave an image whose every command fails at import."""
    import tomllib

    include = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = [pattern.removesuffix("*") for pattern in include]
    assert "agv_protocol" in packages
    copies = {tuple(line.split()[1:]) for line in DOCKERFILE.splitlines() if line.startswith("COPY ")}
    assert [p for p in packages if (p, f"./{p}") not in copies] == []


# ---------------------------------------------------------------- docker-compose.secure.yml (Zenoh's security)

SECURE_COMPOSE = yaml.safe_load((ROOT / "docker-compose.secure.yml").read_text())
SECURE_SERVICES = SECURE_COMPOSE["services"]
SECURE_DIR = ROOT / "deploy" / "zenoh" / "secure"


def mounts(name: str) -> dict[str, Path]:
    """Container path -> host path of a secure compose service's bind mounts (read-only, all of them)."""
    out = {}
    for volume in SECURE_SERVICES[name].get("volumes", []):
        host, container, *mode = volume.split(":")
        if host.startswith("./"):
            assert mode == ["ro"], f"{name}: {volume} must be read-only"
            out[container] = ROOT / host
    return out


def certs_dir() -> Path:
    """Where `make certs` writes (the Makefile's CERTS_DIR)."""
    return ROOT / re.search(r"^CERTS_DIR \?= (\S+)$", (ROOT / "Makefile").read_text(), re.M).group(1)


def identities_issued() -> set[str]:
    """The identities `make certs` issues a directory to: the service, the dashboard and the vehicle list's."""
    from service.zenoh_acl import MONITOR_IDENTITY, SERVICE_IDENTITY, read_vehicle_list

    grants = read_vehicle_list((SECURE_DIR / "vehicles.txt").read_text())
    return {SERVICE_IDENTITY, MONITOR_IDENTITY, *(g.identity for g in grants)}


def mounted_file(name: str, container_path: str) -> Path:
    """The host file behind ``container_path`` in service ``name`` (a file mount, or a file in a dir mount)."""
    for container, host in mounts(name).items():
        if container_path == container:
            return host
        if container_path.startswith(container + "/"):
            return host / container_path.removeprefix(container + "/")
    raise AssertionError(f"{name}: nothing mounted at {container_path}")


def test_secure_compose_has_the_same_roles_and_a_tls_router_with_the_secure_config():
    # the same roles as the plain file's default services (its monitoring profile adds Prometheus and Grafana)
    roles = {name for name, service in SERVICES.items() if "monitoring" not in service.get("profiles", [])}
    assert set(SECURE_SERVICES) == roles
    assert SECURE_COMPOSE["volumes"] == {k: v for k, v in COMPOSE["volumes"].items() if k == "agv-data"}
    router = SECURE_SERVICES["router"]
    assert router["image"] == SERVICES["router"]["image"] and router["command"] == ["-c", "/etc/zenoh/router.json5"]
    assert mounts("router") == {
        "/etc/zenoh/router.json5": SECURE_DIR / "router.json5",
        "/etc/zenoh/certs": certs_dir() / "router",
    }
    config = (SECURE_DIR / "router.json5").read_text()
    (port,) = re.findall(r'"tls/0\.0\.0\.0:(\d+)"', config)
    assert router["ports"] == [f"{port}:{port}"]
    # every file the router config names is in the certificate mount (make certs writes them there)
    for path in re.findall(r'"(/etc/zenoh/certs/[^"]+)"', config):
        assert Path(path).name in {"ca.pem", "router.pem", "router.key", "users.txt"}


def test_secure_service_connects_over_tls_with_its_own_identity():
    env = {k: str(v) for k, v in SECURE_SERVICES["service"]["environment"].items()}
    for variable in env:
        setting_field(variable)  # KeyError if the variable sets nothing
    settings = Settings(**_nested(env))
    assert settings.zenoh.mode == "client" and settings.zenoh.endpoint.startswith("tls/router:")
    port = settings.zenoh.endpoint.rsplit(":", 1)[1]
    assert f"{port}:{port}" in SECURE_SERVICES["router"]["ports"]
    assert mounted_file("service", str(settings.zenoh.config_file)) == SECURE_DIR / "client.json5"
    assert mounted_file("service", str(settings.zenoh.credentials_file)) == certs_dir() / "agv-service" / "credentials"
    # the rest is the plain compose's service
    plain = environment_of("service")
    assert {k: v for k, v in env.items() if "ZENOH" not in k} == {k: v for k, v in plain.items() if "ZENOH" not in k}


@pytest.mark.parametrize(("name", "identity"), [("fleet", "agv-fleet-sim"), ("dashboard", "agv-dashboard")])
def test_secure_edge_commands_parse_and_use_the_client_config_with_their_identity(name: str, identity: str):
    command = [interpolate(str(part)) for part in SECURE_SERVICES[name]["command"]]
    args = build_parser().parse_args(command)
    assert args.command == name
    assert args.connect == [SECURE_SERVICES["service"]["environment"]["AGV_FE_ZENOH__ENDPOINT"]]
    assert args.connect_timeout == -1
    assert mounted_file(name, args.zenoh_config) == SECURE_DIR / "client.json5"
    assert mounted_file(name, args.zenoh_credentials) == certs_dir() / identity / "credentials"
    assert identity in identities_issued()
    if name == "fleet":
        from service.zenoh_acl import read_vehicle_list

        # the fleet's vehicles (PREFIX-000 ...) are the ones the ACL lets its identity publish for, and it
        # sends no ground truth, which no vehicle may put
        allowed = {
            g.vehicle_id for g in read_vehicle_list((SECURE_DIR / "vehicles.txt").read_text()) if g.identity == identity
        }
        assert {f"{args.id_prefix}-{i:03d}" for i in range(args.vehicles)} <= allowed
        assert args.truth_hz == 0


def test_secure_compose_mounts_only_what_make_certs_issues():
    for name in SECURE_SERVICES:
        for host in mounts(name).values():
            if certs_dir() in host.parents:
                assert host.parent == certs_dir() and host.name in identities_issued() | {"router"}
    assert "/secrets/" in (ROOT / ".gitignore").read_text().splitlines()


def test_make_demo_installs_the_runtime_dependencies_only(tmp_path):
    """`make demo` on a fresh machine bootstraps a venv with `pip install -e .` (no dev extras: no pytest,
    Playwright, linters); `make test` with the dev extras. Checked on make's dry run for a venv not yet made."""
    venv = tmp_path / "venv"
    demo = subprocess.run(["make", "-n", "demo", f"VENV={venv}"], cwd=ROOT, capture_output=True, text=True, check=True)
    installs = [line for line in demo.stdout.splitlines() if "pip install" in line and "-e" in line]
    assert installs and all("-e ." in line and "[dev]" not in line for line in installs), demo.stdout
    assert f"{venv}/bin/agv-fe demo" in demo.stdout
    test = subprocess.run(["make", "-n", "test", f"VENV={venv}"], cwd=ROOT, capture_output=True, text=True, check=True)
    assert "-e '.[dev]'" in test.stdout
