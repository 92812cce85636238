"""The dashboard's static files ship in the wheel: an installed service serves the page without the source tree."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "service" / "web" / "static"


def test_every_static_file_is_in_the_wheel(tmp_path):
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--quiet", "--wheel-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr
    (wheel,) = tmp_path.glob("*.whl")
    shipped = set(zipfile.ZipFile(wheel).namelist())
    expected = {p.relative_to(ROOT).as_posix() for p in STATIC.rglob("*") if p.is_file()}
    assert {"service/web/static/index.html", "service/web/static/vendor/uplot/LICENSE"} <= expected
    assert expected <= shipped, sorted(expected - shipped)


def test_the_wheel_carries_the_licence_and_the_type_markers(tmp_path):
    """pyproject declares Apache-2.0 and typed packages: the wheel ships the licence text and py.typed files."""
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--quiet", "--wheel-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr
    (wheel,) = tmp_path.glob("*.whl")
    shipped = set(zipfile.ZipFile(wheel).namelist())
    assert {f"{package}/py.typed" for package in ("synth", "service", "edge_client", "agv_fe")} <= shipped
    licences = [name for name in shipped if name.endswith("/LICENSE") and ".dist-info/" in name]
    assert licences, sorted(n for n in shipped if "dist-info" in n)
    text = zipfile.ZipFile(wheel).read(licences[0]).decode()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
