"""include/agv_fe/measurement.h against agv_protocol/wire.py, byte for byte: the C example (examples/c/) compiled with
the system's C compiler encodes samples exactly as Measurement.encode() and gives the same key expressions and
buckets, and decodes Python's payloads to the same numbers, refusing what the service refuses."""

from __future__ import annotations

import math
import re
import shlex
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from agv_protocol.wire import Measurement, bucket_of, vehicle_key

ROOT = Path(__file__).resolve().parent.parent
COMPILER = shutil.which("cc") or shutil.which("gcc")
ERRORS = {"id": -1, "size": -3, "magic": -4, "version": -5, "reserved": -6}


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    if COMPILER is None:
        pytest.fail("no C compiler (cc or gcc): .ci/install-system-deps installs gcc")
    binary = tmp_path_factory.mktemp("c") / "agv_fe_example"
    command = [COMPILER, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-I", str(ROOT / "include"),
               str(ROOT / "examples/c/agv_fe_example.c"), "-o", str(binary)]  # fmt: skip
    built = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert built.returncode == 0, built.stderr
    return binary


def _run(binary: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(binary), *args], capture_output=True, text=True, timeout=30)


def _cases() -> list[Measurement]:
    rng = np.random.default_rng(0)
    ids = ["truck-7", "a", "A" * 64, "AGV_01.north-dock", "b0f", "x.y_z-9"]
    cases = [Measurement(vid, int(rng.integers(0, 2**40)), 1_700_000_000_000_000_000 + int(rng.integers(0, 10**12)),
                         *map(float, rng.normal(0, 50, 4))) for vid in ids]  # fmt: skip
    edges = [0.0, -0.0, 5e-324, -1.7976931348623157e308, 1e-300, math.pi]
    cases.append(Measurement("edge", 2**64 - 1, -(2**63), *edges[:4]))
    cases.append(Measurement("edge", 0, 0, *edges[2:], flags=1))
    cases.append(Measurement("hill", 7, 1, 12.0, 0.01, 480.0, 0.002, grade_rad=0.052359877559829883))
    cases.append(Measurement("dip", 0, 2, 9.0, -0.02, -150.0, -0.001, flags=1, grade_rad=-0.0))
    return cases


def test_the_c_encoder_writes_the_python_bytes_and_keys(example):
    for m in _cases():
        grade = [] if m.grade_rad is None else [repr(m.grade_rad)]
        out = _run(example, "encode", m.vehicle_id, str(m.seq), str(m.timestamp_ns),
                   *(repr(v) for v in (m.vx_mps, m.r_radps, m.torque_nm, m.steer_rad)), *grade)  # fmt: skip
        assert out.returncode == 0, out.stderr
        key, payload = out.stdout.split()
        expected = Measurement(m.vehicle_id, m.seq, m.timestamp_ns, m.vx_mps, m.r_radps, m.torque_nm, m.steer_rad,
                               flags=1 if m.seq == 0 else 0, grade_rad=m.grade_rad)  # fmt: skip
        assert payload == expected.encode().hex(), m
        assert key == vehicle_key(m.vehicle_id, "meas") and key.split("/")[2] == bucket_of(m.vehicle_id)
    assert (
        _run(example, "encode", "truck-7", "1", "0", "0", "0", "0", "0").stdout.split()[0] == "agv/v1/b0f/truck-7/meas"
    )
    for bad in ("", "a/b", "é", "A" * 65, "truck 7"):
        assert _run(example, "encode", bad, "1", "0", "0", "0", "0", "0").returncode == 1, bad


def _decoded(example: Path, payload: bytes) -> str:
    out = _run(example, "decode", payload.hex())
    return out.stdout.strip()


def test_the_c_decoder_reads_python_payloads_and_refuses_what_the_service_refuses(example):
    for m in _cases():
        fields = _decoded(example, m.encode()).split()
        flags = m.flags | (2 if m.grade_rad is not None else 0)
        assert fields[:4] == [m.vehicle_id, str(flags), str(m.seq), str(m.timestamp_ns)]
        got = [float(v) for v in fields[4:]]
        expected = [m.vx_mps, m.r_radps, m.torque_nm, m.steer_rad, *([] if m.grade_rad is None else [m.grade_rad])]
        assert [struct.pack("<d", v) for v in got] == [struct.pack("<d", v) for v in expected], m
    good = bytearray(Measurement("truck-7", 5, 1, 1.0, 0.0, 0.0, 0.0).encode())
    refused = {
        "magic": b"AGVX" + good[4:],
        "version": good[:4] + b"\x02" + good[5:],
        "reserved": good[:5] + b"\x04" + good[6:],  # flag bit 2
        "size": good[:-1],
    }
    refused_reserved_bytes = good[:56] + b"\x01" + good[57:]
    refused_id = good[:64] + b"truck/7"
    for reason, payload in refused.items():
        assert _decoded(example, bytes(payload)) == f"error {ERRORS[reason]}", reason
    assert _decoded(example, bytes(refused_reserved_bytes)) == f"error {ERRORS['reserved']}"
    assert _decoded(example, bytes(refused_id)) == f"error {ERRORS['id']}"


def test_the_example_of_docs_integration_md_runs_as_printed(tmp_path):
    """The page's two commands, run verbatim in a copy of include/ and examples/, print the page's output."""
    if COMPILER is None:
        pytest.fail("no C compiler (cc or gcc): .ci/install-system-deps installs gcc")
    text = (ROOT / "docs/integration.md").read_text()
    section = text[text.index("\n## C\n") : text.index("\n## Plain Zenoh\n")]
    (commands,) = re.findall(r"```sh\n(.*?)```", section, re.S)
    (expected,) = re.findall(r"```text\n(.*?)```", section, re.S)
    shutil.copytree(ROOT / "include", tmp_path / "include")
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    outputs = []
    for line in commands.splitlines():
        argv = shlex.split(line)
        argv[0] = COMPILER if argv[0] == "cc" else str(tmp_path / argv[0])
        done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, (line, done.stderr)
        outputs.append(done.stdout)
    assert "".join(outputs) == expected


def test_the_c_estimate_decoder_reads_python_binary_estimates_and_refuses_what_python_refuses(example):
    """include/agv_fe/estimate.h: every field of agv_protocol/wire.py's binary estimate, bit for bit, NaN for the
    columns a record does not carry; the C column list is the Python one."""
    from agv_protocol.wire import (
        ESTIMATE_COLUMNS,
        ESTIMATE_REVISION,
        STATE_COLUMNS,
        EstimateBatch,
        ProtocolError,
        decode_binary_estimate,
        encode_binary_estimates,
        level_codes,
    )

    header = (ROOT / "include/agv_fe/estimate.h").read_text()
    names = re.findall(r"AGV_FE_COLUMN_(\w+) = (\d+)", header)
    assert [(name.lower(), int(i)) for name, i in names] == [(c, i) for i, c in enumerate(ESTIMATE_COLUMNS)]
    assert f"#define AGV_FE_ESTIMATE_REVISION {ESTIMATE_REVISION}\n" in header
    rng = np.random.default_rng(1)
    for columns, fast in ((STATE_COLUMNS, None), (ESTIMATE_COLUMNS, np.array([True, False, True]))):
        batch = EstimateBatch(["a", "b", "c"], np.array([0, 2**63 + 5, 17]), np.array([-(2**63), 0, 2**62]),
                              rng.normal(0, 100, (3, len(columns))), np.array([True, False, True]),
                              level_codes(["OK", "FAULT", "STALE"]), "3f9a1c0b7d2e", fast, columns)  # fmt: skip
        for payload in encode_binary_estimates(batch):
            fields = _run(example, "decode-estimate", payload.hex()).stdout.split()
            record = np.frombuffer(payload, np.dtype([("h", "V40"), ("v", "<f8", (len(columns),))]))[0]
            assert [int(v) for v in fields[:5]] == [payload[5], payload[6], payload[7],
                                                    int.from_bytes(payload[8:16], "little"),
                                                    int.from_bytes(payload[16:24], "little", signed=True)]  # fmt: skip
            assert fields[5] == "3f9a1c0b7d2e"
            got = [float(v) for v in fields[6:]]
            expected = [*record["v"].tolist(), *[math.nan] * (len(ESTIMATE_COLUMNS) - len(columns))]
            assert [struct.pack("<d", v) for v in got[: len(columns)]] == [
                struct.pack("<d", v) for v in expected[: len(columns)]
            ]
            assert all(math.isnan(v) for v in got[len(columns) :])
    good = encode_binary_estimates(EstimateBatch(["a"], np.array([1]), np.array([2]), np.ones((1, 5)),
                                                 np.array([True]), level_codes(["OK"]), "v"))[0]  # fmt: skip
    refused = {
        "size": good[:-8],
        "magic": b"AGVX" + good[4:],
        "version": good[:4] + b"\x02" + good[5:],
        "reserved": good[:6] + b"\x08" + good[7:],
    }
    for reason, payload in refused.items():
        assert _decoded_estimate(example, payload) == f"error {ERRORS[reason]}", reason
        with pytest.raises(ProtocolError):
            decode_binary_estimate(payload, "a")
    assert _decoded_estimate(example, good[:7] + b"\x04" + good[8:]) == "error -7"  # no level 4


def _decoded_estimate(example: Path, payload: bytes) -> str:
    return _run(example, "decode-estimate", payload.hex()).stdout.strip()
