import subprocess
import sys


def test_synth_imports_neither_fastapi_nor_zenoh():
    """synth/ is pure math: importing all of it must not pull in the web or transport layers."""
    code = (
        "import sys, pkgutil, importlib, synth\n"
        "for m in pkgutil.walk_packages(synth.__path__, 'synth.'): importlib.import_module(m.name)\n"
        "web = {'fastapi', 'zenoh', 'uvicorn', 'starlette', 'httpx'}\n"
        "bad = sorted(n for n in sys.modules if n.split('.')[0] in web)\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_the_runtime_observer_does_not_import_the_solvers():
    """Gains, their verification and the observer step serve the service, replay and the vehicles: they load
    without cvxpy and its solvers (half a second and tens of MB), which only a synthesis needs."""
    code = (
        "import sys, synth.gains, synth.observer, synth.certificate, synth.calibration, service.fleet\n"
        "print(','.join(sorted(n for n in sys.modules if n.split('.')[0] in {'cvxpy', 'clarabel', 'scs'})))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
