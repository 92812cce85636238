"""TEST-ONLY: a zenoh router in its own process, killable to test reconnection.

Usage: python tests/edge_client/zenoh_router.py PORT. Listens on
tcp/127.0.0.1:PORT with multicast scouting off, prints "ready" once open, and
closes its session on SIGTERM (SIGKILL simulates a crash).
"""

from __future__ import annotations

import json
import signal
import sys
import threading

import zenoh


def main(port: int) -> None:
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print("ready", flush=True)
    try:
        # bounded even if nobody stops it: a forgotten router exits after 10 minutes
        stop.wait(timeout=600)
    finally:
        session.close()


if __name__ == "__main__":
    main(int(sys.argv[1]))
