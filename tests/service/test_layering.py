"""The service's layers: only transport.py imports zenoh; the fleet state needs no web, transport or storage."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

SERVICE = Path(__file__).resolve().parents[2] / "service"


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_only_the_transport_module_imports_zenoh():
    importers = sorted(
        p.relative_to(SERVICE).as_posix() for p in SERVICE.rglob("*.py") if "zenoh" in imported_modules(p)
    )
    assert importers == ["transport.py"]


def test_the_protocol_and_the_fleet_import_neither_web_nor_transport_nor_storage():
    code = (
        "import sys, agv_protocol.wire, service.fleet\n"
        "heavy = {'fastapi', 'zenoh', 'uvicorn', 'starlette', 'sqlite3'}\n"
        "bad = sorted(n for n in sys.modules if n.split('.')[0] in heavy)\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
