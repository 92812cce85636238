"""agv_protocol keeps zenoh in its session module: the wire protocol itself loads neither Zenoh nor either side."""

import subprocess
import sys
from pathlib import Path

from tests.service.test_layering import imported_modules

PACKAGE = Path(__file__).resolve().parents[2] / "agv_protocol"


def test_only_the_session_module_imports_zenoh():
    """zenoh_session.py holds the Zenoh session configuration and the transport error both sides use (the service's
    transport and the vehicles' import it), so it imports zenoh; the wire protocol does not."""
    importers = sorted(p.name for p in PACKAGE.glob("*.py") if "zenoh" in imported_modules(p))
    assert importers == ["zenoh_session.py"]


def test_the_wire_protocol_loads_no_zenoh_and_neither_side():
    code = (
        "import sys, agv_protocol.wire\n"
        "heavy = {'zenoh', 'fastapi', 'service', 'edge_client', 'agv_fe', 'synth'}\n"
        "print(','.join(sorted(n for n in sys.modules if n.split('.')[0] in heavy)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
