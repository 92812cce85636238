"""What the wheel ships: the dashboard's static files (an installed service serves the page without the source
tree), the licence pyproject declares and the py.typed markers of the typed packages."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "service" / "web" / "static"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> zipfile.ZipFile:
    """The project's wheel, built once for the module."""
    out = tmp_path_factory.mktemp("wheel")
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--quiet", "--wheel-dir", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr
    (path,) = out.glob("*.whl")
    return zipfile.ZipFile(path)


def test_every_static_file_is_in_the_wheel(wheel: zipfile.ZipFile) -> None:
    shipped = set(wheel.namelist())
    expected = {p.relative_to(ROOT).as_posix() for p in STATIC.rglob("*") if p.is_file()}
    assert {"service/web/static/index.html", "service/web/static/vendor/uplot/LICENSE"} <= expected
    assert expected <= shipped, sorted(expected - shipped)


def test_the_wheel_carries_the_licence_and_the_type_markers(wheel: zipfile.ZipFile) -> None:
    """pyproject declares Apache-2.0 and typed packages: the wheel ships the licence text and py.typed files."""
    shipped = set(wheel.namelist())
    packages = ("synth", "agv_protocol", "service", "edge_client", "agv_fe")
    assert {f"{package}/py.typed" for package in packages} <= shipped
    licences = [name for name in shipped if name.endswith("/LICENSE") and ".dist-info/" in name]
    assert licences, sorted(n for n in shipped if "dist-info" in n)
    text = wheel.read(licences[0]).decode()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
