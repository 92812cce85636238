"""`agv-fe serve`: the cloud service (FastAPI on uvicorn plus a Zenoh session)."""

from __future__ import annotations

import argparse
from typing import Any

#: How long a shutdown waits for open HTTP responses before it cuts them [s].
GRACEFUL_SHUTDOWN_S = 5
#: Exit status when a background task (ingest, housekeeping) could not be kept running.
EXIT_SERVICE_FAILED = 4


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "serve",
        help="run the fleet service: Zenoh ingest, observers, alarms, REST API",
        description="Run the service. Settings come from AGV_FE_* environment variables (nested with '__', "
        "see docs/service.md, 'Settings'); these flags override them.",
    )
    parser.add_argument("--http-port", type=int, default=None, metavar="PORT", help="HTTP port (AGV_FE_HTTP__PORT)")
    parser.add_argument("--http-host", default=None, metavar="HOST", help="HTTP bind address (AGV_FE_HTTP__HOST)")
    parser.add_argument(
        "--zenoh-endpoint",
        default=None,
        metavar="tcp/HOST:PORT",
        help="where the in-process router listens, or the router a client connects to (AGV_FE_ZENOH__ENDPOINT)",
    )
    parser.add_argument(
        "--zenoh-mode", choices=("router", "client"), default=None, help="Zenoh mode (AGV_FE_ZENOH__MODE)"
    )
    parser.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE.json5",
        help="Zenoh configuration file: TLS, user/password, access control (AGV_FE_ZENOH__CONFIG_FILE; "
        "docs/deployment.md)",
    )
    parser.add_argument(
        "--zenoh-credentials",
        default=None,
        metavar="FILE",
        help="USER:PASSWORD for Zenoh's user/password authentication (AGV_FE_ZENOH__CREDENTIALS_FILE)",
    )
    parser.add_argument("--data-dir", default=None, metavar="DIR", help="database directory (AGV_FE_DATA_DIR)")
    parser.add_argument(
        "--database-url",
        default=None,
        metavar="URL",
        help="PostgreSQL shared by the replicas, postgresql://USER@HOST:PORT/DATABASE, instead of the SQLite file "
        "in --data-dir (AGV_FE_DATABASE__URL; give a password there, not on the command line)",
    )
    parser.add_argument("--profiles", default=None, metavar="FILE", help="initial profiles (AGV_FE_PROFILES_FILE)")
    parser.add_argument(
        "--shard",
        default=None,
        metavar="INDEX/REPLICAS",
        help="serve shard INDEX of REPLICAS, e.g. 0/2 (AGV_FE_SHARD__INDEX, AGV_FE_SHARD__REPLICAS); without it, "
        "replicas sharing a --database-url share the buckets by leases (AGV_FE_SHARD__MODE)",
    )
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    parser.add_argument(
        "--log-format",
        default="text",
        choices=("text", "json"),
        help="json: one JSON object per line for every log record, alarm and job events and the access log included",
    )
    parser.set_defaults(handler=run)


def build_settings(args: argparse.Namespace) -> Any:
    """Settings from the environment, overridden by the flags that were given."""
    from pydantic import ValidationError

    from agv_fe.common import CommandError, validation_message
    from service.settings import Settings

    overrides: dict[str, Any] = {}
    if args.http_port is not None or args.http_host is not None:
        overrides["http"] = {k: v for k, v in (("port", args.http_port), ("host", args.http_host)) if v is not None}
    zenoh_flags = (
        ("endpoint", args.zenoh_endpoint),
        ("mode", args.zenoh_mode),
        ("config_file", args.zenoh_config),
        ("credentials_file", args.zenoh_credentials),
    )
    zenoh = {k: v for k, v in zenoh_flags if v is not None}
    if zenoh:
        overrides["zenoh"] = zenoh
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    if args.profiles is not None:
        overrides["profiles_file"] = args.profiles
    if args.database_url is not None:
        overrides["database"] = {"url": args.database_url}
    if args.shard is not None:
        try:
            index, replicas = (int(x) for x in args.shard.split("/"))
        except ValueError:
            raise CommandError(f"--shard: expected INDEX/REPLICAS such as 0/2, got {args.shard!r}") from None
        overrides["shard"] = {"index": index, "replicas": replicas, "mode": "static"}
    try:
        base = Settings()
        merged = base.model_dump()
        for key, value in overrides.items():
            if isinstance(value, dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        if base.auth.token is not None:
            merged["auth"]["token"] = base.auth.token.get_secret_value()
        if "database" not in overrides and base.database.url is not None:
            merged["database"]["url"] = base.database.url.get_secret_value()
        return Settings.model_validate(merged)
    except ValidationError as exc:
        raise CommandError(f"invalid settings:\n{validation_message(exc, '')}") from exc


def check_zenoh_config(settings: Any) -> None:
    """Read the Zenoh configuration file (if any) before starting, so that a wrong key, a missing file or a
    conflict with the mode or endpoint is a one-line error instead of a failed start-up."""
    from agv_fe.common import CommandError
    from agv_protocol.zenoh_session import TransportError
    from service.transport import zenoh_config

    z = settings.zenoh
    if z.config_file is None and z.credentials_file is None:
        return
    try:
        zenoh_config(
            z.mode, z.endpoint, z.connect_timeout_ms, config_file=z.config_file, credentials_file=z.credentials_file
        )
    except TransportError as exc:
        raise CommandError(str(exc)) from exc


def pin_to_cpus(settings: Any) -> None:
    """Move this process to the CPUs of setting ``cpus`` (service/affinity.py); CommandError naming the setting
    when a CPU is not one the process may use or the system refuses."""
    from agv_fe.common import CommandError
    from service.affinity import pin_process

    cpus = settings.cpu_set
    if cpus is None:
        return
    try:
        pin_process(cpus)
    except (ValueError, OSError) as exc:
        raise CommandError(f"setting cpus ({settings.cpus!r}): {exc}") from exc


def run(args: argparse.Namespace) -> int:
    import logging

    import uvicorn

    from agv_fe.common import CommandError, fail
    from service import logs
    from service.main import create_app
    from service.transport import apply_runtime_threads

    try:
        settings = build_settings(args)
        # before anything in this process opens Zenoh: its runtimes read their threads once
        runtime = apply_runtime_threads(settings.zenoh.runtime_threads)
        check_zenoh_config(settings)
        pin_to_cpus(settings)  # before Zenoh and the service start their threads: they inherit the CPUs
    except CommandError as exc:
        return fail(exc)
    logs.configure(args.log_level, args.log_format)
    log = logging.getLogger("agv_fe.service")
    log.info("Zenoh runtime threads: %s", runtime or "Zenoh's defaults")
    if settings.cpus is not None:
        log.info("running on CPUs %s (setting cpus)", settings.cpus)
    app = create_app(settings)

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: Any) -> None:
            # open dashboard streams never end by themselves: end them, or the shutdown waits for them
            service = getattr(app.state, "service", None)
            if service is not None:
                service.dashboard.end_streams_threadsafe()
            super().handle_exit(sig, frame)

    config = uvicorn.Config(
        app,
        host=settings.http.host,
        port=settings.http.port,
        log_level=args.log_level,
        log_config=None,  # uvicorn's records go to the handler service.logs.configure set up, in its format
        lifespan="on",
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
    )
    server = Server(config)

    def stop_failed_service() -> None:
        server.should_exit = True  # the same graceful shutdown as SIGTERM

    app.state.on_fatal = stop_failed_service
    server.run()
    service = getattr(app.state, "service", None)
    if service is not None and service.fatal is not None:
        logging.getLogger("agv_fe.service").critical("exiting with status %d: %s", EXIT_SERVICE_FAILED, service.fatal)
        return EXIT_SERVICE_FAILED
    return 0
