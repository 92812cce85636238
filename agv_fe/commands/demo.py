"""`agv-fe demo`: the service, a simulated fleet and the dashboards, on one machine, in one command.

The service (`agv-fe serve`, in-process Zenoh router on loopback, SQLite in a
data directory) and the fleet (`agv-fe fleet`, a client of that router) run as
child processes in their own sessions; the terminal dashboard runs in the
foreground. Ctrl-C (or the end of ``--duration``) stops the fleet first, which
writes its per-vehicle summary (injected faults against what the service
estimated and alarmed), then the service. SIGTERM and SIGHUP (the terminal
closed) stop it the same way: the children are in sessions of their own, so
no signal of the terminal reaches them, and nothing is left running.
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from agv_fe.common import CommandError, fail

DEFAULT_HTTP_PORT = 8080
DEFAULT_ZENOH_PORT = 7447
#: The fleet of an open-ended demo runs this long unless stopped earlier [s].
OPEN_ENDED_S = 24 * 3600.0
READY_TIMEOUT_S = 180.0
#: Signals that stop the demo in order, as Ctrl-C does: `kill` (SIGTERM) and a closed terminal (SIGHUP) too.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "demo",
        help="run the service, a simulated fleet and the dashboards (what `make demo` runs)",
        description="Start the service (in-process Zenoh router on 127.0.0.1, SQLite in a data directory), a "
        "simulated fleet of healthy and faulty vehicles publishing at 100 Hz, and a live terminal dashboard; "
        "print the web dashboard's URL. Ctrl-C, or the end of --duration, stops everything and prints, per "
        "vehicle, the injected fault against what the service estimated and alarmed.",
    )
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--vehicles", type=int, default=20, help="fleet size (default 20)")
    parser.add_argument(
        "--scenario-mix",
        default="healthy=0.4,torque_bias=0.15,torque_loe=0.1,steer_bias=0.15,steer_sinusoidal=0.1,intermittent=0.1",
        help="weights of the vehicle kinds (see agv-fe fleet --help)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the drives, faults and noise")
    parser.add_argument(
        "--level-empty",
        action="store_true",
        help="vehicles empty on level ground (by default each carries a random load and drives hills, reporting "
        "both: agv-fe fleet --loads --hills)",
    )
    parser.add_argument(
        "--data-dir", default=None, metavar="DIR", help="service data (default: a new temporary directory)"
    )
    parser.add_argument("--http-port", type=int, default=DEFAULT_HTTP_PORT, help="HTTP port (a free one if busy or 0)")
    parser.add_argument(
        "--zenoh-port", type=int, default=DEFAULT_ZENOH_PORT, help="Zenoh router port (a free one if busy or 0)"
    )
    parser.add_argument("--summary-json", metavar="FILE", help="also write the fleet summary as JSON")
    parser.add_argument(
        "--no-dashboard", action="store_true", help="no terminal dashboard (also off a terminal), only the summary"
    )
    parser.set_defaults(handler=run)


def port_or_free(port: int) -> int:
    """``port`` if nothing listens on 127.0.0.1:port, else (or for 0) a free port."""
    if port:
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
                return port
            except OSError:
                pass
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _child(command: list[str], log: TextIO) -> subprocess.Popen[bytes]:
    """A child in its own session: the terminal's Ctrl-C reaches only the demo, which stops it in order."""
    return subprocess.Popen(
        [sys.executable, "-m", "agv_fe", *command],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def _stop(process: subprocess.Popen[bytes], sig: int, timeout_s: float) -> None:
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)


def _wait_ready(url: str, service: subprocess.Popen[bytes], log_path: Path, stop: threading.Event) -> None:
    import httpx

    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline and not stop.is_set():
        if service.poll() is not None:
            raise CommandError(f"the service exited with code {service.returncode}; its log: {log_path}")
        try:
            if httpx.get(f"{url}/ready", timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.25)
    raise CommandError(f"the service was not ready within {READY_TIMEOUT_S:.0f} s; its log: {log_path}")


def _check_args(args: argparse.Namespace) -> None:
    """Raise :class:`CommandError` naming the option out of its range."""
    if args.duration is not None and not 5 <= args.duration <= OPEN_ENDED_S:
        raise CommandError(f"--duration: expected 5 to {OPEN_ENDED_S:.0f} seconds, got {args.duration}")
    if not 1 <= args.vehicles <= 2000:
        raise CommandError(f"--vehicles: expected 1 to 2000, got {args.vehicles}")


def _fleet_arguments(args: argparse.Namespace, endpoint: str, summary_path: Path) -> list[str]:
    """`agv-fe fleet`'s command line: the demo's vehicles for its duration (open-ended without one)."""
    duration = args.duration if args.duration is not None else OPEN_ENDED_S
    return [
        "fleet",
        "--vehicles",
        str(args.vehicles),
        "--duration",
        str(duration),
        "--scenario-mix",
        args.scenario_mix,
        "--seed",
        str(args.seed),
        "--connect",
        endpoint,
        "--summary-json",
        str(summary_path),
        *([] if args.level_empty else ["--loads", "--hills"]),
    ]


def _announce(args: argparse.Namespace, url: str, endpoint: str, data_dir: Path) -> None:
    """Where to look: the web dashboard, the REST API and its token, the terminal view, the logs."""
    token_file = data_dir / "api-token"
    print(f"web dashboard     {url}/")
    print(f"REST API          {url}/docs  (write token in {token_file})")
    print(f"terminal view     agv-fe dashboard --connect {endpoint}")
    print(f"logs              {data_dir / 'service.log'}, {data_dir / 'fleet.log'}")
    print(
        f"{args.vehicles} simulated vehicles at 100 Hz "
        + (f"for {args.duration:g} s" if args.duration is not None else "until Ctrl-C"),
        flush=True,
    )


def run(args: argparse.Namespace) -> int:
    try:
        _check_args(args)
    except CommandError as exc:
        return fail(exc)
    data_dir = Path(args.data_dir) if args.data_dir else Path(tempfile.mkdtemp(prefix="agv-fe-demo-"))
    data_dir.mkdir(parents=True, exist_ok=True)
    http_port = port_or_free(args.http_port)
    zenoh_port = port_or_free(args.zenoh_port)
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    url = f"http://127.0.0.1:{http_port}"
    summary_path = Path(args.summary_json) if args.summary_json else data_dir / "fleet-summary.json"
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in STOP_SIGNALS}
    service_log = (data_dir / "service.log").open("w")
    fleet_log = (data_dir / "fleet.log").open("w")
    service: subprocess.Popen[bytes] | None = None
    fleet: subprocess.Popen[bytes] | None = None
    try:
        print(f"agv-fe demo: data in {data_dir}")
        print(f"starting the service (HTTP {url}, Zenoh router {endpoint}) ...", flush=True)
        service = _child(
            ["serve", "--http-port", str(http_port), "--zenoh-endpoint", endpoint, "--data-dir", str(data_dir)],
            service_log,
        )
        _wait_ready(url, service, data_dir / "service.log", stop)
        if stop.is_set():
            return 130
        fleet = _child(_fleet_arguments(args, endpoint, summary_path), fleet_log)
        _announce(args, url, endpoint, data_dir)
        threading.Thread(target=_set_when_done, args=(fleet, stop), daemon=True).start()
        if args.no_dashboard or not sys.stdout.isatty():
            stop.wait()  # off a terminal the summary below is the report
        else:
            _dashboard(endpoint, stop)
        print("stopping ...", flush=True)
        _stop(fleet, signal.SIGINT, timeout_s=60)  # the fleet ends early on SIGINT and writes its summary
        fleet_log.flush()
        _print_fleet_summary(data_dir / "fleet.log")
        print(SUMMARY_LEGEND)
        kept = f"service.sqlite3 (the service's database), service.log, fleet.log, {summary_path.name}"
        print(f"kept in {data_dir}: {kept}")
        if fleet.returncode not in (0, -signal.SIGINT, 130):
            return fail(CommandError(f"the fleet exited with code {fleet.returncode}; its log: {fleet_log.name}"))
        return 0 if summary_path.exists() else 1
    except CommandError as exc:
        return fail(exc)
    finally:
        if fleet is not None:  # still running after an error (a closed terminal fails every print): its summary
            _stop(fleet, signal.SIGINT, timeout_s=60)
        if service is not None:
            _stop(service, signal.SIGTERM, timeout_s=30)
        service_log.close()
        fleet_log.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


#: What the fleet summary's columns and totals mean, printed under it.
SUMMARY_LEGEND = (
    "columns: injected = the fault the vehicle's simulator added; est. peak = the largest |T_f| [N m] / |delta_f| "
    "[rad] the service estimated after the onset; quiet peak = the same before the onset and on healthy vehicles "
    "(what a false alarm would have to exceed); alarm = the fault alarms raised (FALSE: on a healthy channel); "
    "after = from the onset to the first alarm.\n"
    "totals: late ticks = publisher ticks that started over 1 ms late, overruns = ticks that started after the "
    "next one was due (the machine fell behind); lost = samples never sent (dropped from a vehicle's full buffer "
    "while nothing could receive them); estimates = the estimates that came back (one per sample sent); round "
    "trip = sample sent to its estimate received."
)


def _set_when_done(process: subprocess.Popen[bytes], stop: threading.Event) -> None:
    process.wait()
    stop.set()


def _dashboard(endpoint: str, stop: threading.Event) -> None:
    """The live terminal table in the foreground until ``stop``."""
    from agv_protocol.zenoh_session import TransportError
    from edge_client.dashboard import run_dashboard
    from edge_client.transport import TransportOptions, close_session, open_session

    try:
        session = open_session(TransportOptions(mode="client", connect=(endpoint,)))
    except TransportError as exc:
        print(f"terminal dashboard unavailable: {exc}", file=sys.stderr)
        stop.wait()
        return
    try:
        run_dashboard(session, "agv", refresh_hz=2.0, stop=stop)
    finally:
        close_session(session)


def _print_fleet_summary(log_path: Path) -> None:
    """The fleet's own end-of-run report: its per-vehicle table and totals line."""
    text = log_path.read_text()
    start = text.find("fleet summary")
    if start < 0:
        print(f"the fleet wrote no summary; see {log_path}")
        return
    line_start = text.rfind("\n", 0, start) + 1
    print(text[line_start:], end="")
