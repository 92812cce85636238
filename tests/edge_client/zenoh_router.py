"""TEST-ONLY: a zenoh router in its own process, killable to test reconnection.

Usage: python tests/edge_client/zenoh_router.py PORT|ENDPOINT [CONFIG.json5].
Listens on tcp/127.0.0.1:PORT (or on ENDPOINT, such as tls/127.0.0.1:PORT)
with multicast scouting off, prints "ready" once open, and closes its session
on SIGTERM (SIGKILL simulates a crash). With a config file (e.g.
deploy/zenoh/router.json5, the compose router's, or the secure router's with
its certificate paths made local), it starts from that file and only the
listen endpoint is replaced.
"""

from __future__ import annotations

import json
import signal
import sys
import threading

import zenoh


def main(listen: str, config_file: str | None = None) -> None:
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    endpoint = listen if "/" in listen else f"tcp/127.0.0.1:{int(listen)}"
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
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
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None)
