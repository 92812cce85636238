"""edge_client keeps zenoh in its transport module: the simulator and scenarios stay transport-free."""

import ast
import subprocess
import sys
from pathlib import Path

EDGE = Path(__file__).parents[2] / "edge_client"
ZENOH_FREE = (
    "edge_client.plant",
    "edge_client.scenario",
    "edge_client.faults",
    "edge_client.library",
    "edge_client.random_drive",
    "edge_client.fleet_mix",
    "edge_client.sources",
    "edge_client.pacing",
    "edge_client.stats",
    "edge_client.simulation",
    "edge_client.recording",
)


def test_simulation_and_scenario_modules_do_not_load_zenoh():
    code = (
        "import importlib, sys\n"
        f"for name in {ZENOH_FREE!r}: importlib.import_module(name)\n"
        "print(','.join(sorted(n for n in sys.modules if n.split('.')[0] == 'zenoh')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _runtime_zenoh_imports(path: Path) -> bool:
    """True if the module imports zenoh outside an ``if TYPE_CHECKING:`` block."""
    tree = ast.parse(path.read_text())
    type_only = {
        id(node)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and isinstance(block.test, ast.Name) and block.test.id == "TYPE_CHECKING"
        for node in ast.walk(block)
    }
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "zenoh" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "zenoh":
            return True
    return False


def test_only_the_transport_module_imports_zenoh():
    importers = sorted(p.name for p in EDGE.glob("*.py") if _runtime_zenoh_imports(p))
    assert importers == ["transport.py"]
