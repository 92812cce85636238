"""Request bodies on the real uvicorn server: a body over the limit is refused unread (413), a change without the
token is refused before its body is read (401), and a 422 never repeats a large input."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.service.helpers import TOKEN, WAIT_S, make_settings, running

pytestmark = pytest.mark.network

MIB = 1 << 20


def test_bodies_over_the_limit_and_changes_without_the_token_are_refused_before_the_body_is_read(
    tmp_path: Path,
) -> None:
    with running(make_settings(tmp_path)) as srv:
        auth = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        big = b"x" * (10 * MIB)
        # unauthenticated, 10 MB: 413 from the Content-Length alone
        answer = srv.http.put("/profiles/big", content=big, headers={"Content-Type": "application/json"})
        assert answer.status_code == 413 and "larger than 1048576 bytes" in answer.json()["detail"]
        # with the token too
        assert srv.http.put("/profiles/big", content=big, headers=auth).status_code == 413

        # chunked (no Content-Length): counted while read, refused once past the limit
        def chunks() -> Iterator[bytes]:
            for _ in range(40):
                yield b" " * (64 * 1024)

        chunked = srv.http.put("/profiles/big", content=chunks(), headers=auth)
        assert chunked.status_code == 413
        # a change without the token is 401 before its body is parsed: not a 422 about the (bad) JSON
        refused = srv.http.put(
            "/profiles/big", content=b"{not json" * 1000, headers={"Content-Type": "application/json"}
        )
        assert refused.status_code == 401 and refused.headers["WWW-Authenticate"] == "Bearer"
        wrong = srv.http.put(
            "/vehicles/v-1", json={"profile": "default"}, headers={"Authorization": "Bearer not-the-token"}
        )
        assert wrong.status_code == 401 and wrong.json()["detail"] == "invalid bearer token"
        # the calibration route takes recordings: a body over the general limit reaches its validation (422)
        calibration = srv.http.post("/profiles/default/calibration", content=b"[" + b"1," * MIB + b"1]", headers=auth)
        assert calibration.status_code == 422
        # the service works on
        assert srv.get("/ready").status_code == 200
        assert srv.http.put("/vehicles/v-1", json={"profile": "default"}, headers=auth).status_code == 200


def test_a_validation_error_does_not_repeat_a_large_input(tmp_path: Path) -> None:
    with running(make_settings(tmp_path)) as srv:
        auth = {"Authorization": f"Bearer {TOKEN}"}
        answer = srv.http.put("/vehicles/v-1", json=["n" * 300_000], headers=auth)  # a list, not an object
        assert answer.status_code == 422
        assert len(answer.content) < 2_000, len(answer.content)
        (error,) = answer.json()["detail"]
        assert error["loc"] == ["body"] and "300004 characters, not repeated" in error["input"]
        # a short input is repeated as it was
        short = srv.http.put("/vehicles/v-1", json=[7], headers=auth)
        assert short.status_code == 422 and short.json()["detail"][0]["input"] == [7]


def test_the_openapi_document_names_the_413_of_every_body(tmp_path: Path) -> None:
    with running(make_settings(tmp_path), ready=False) as srv:
        paths = srv.get("/openapi.json").json()["paths"]
        assert "413" in paths["/profiles/{name}"]["put"]["responses"]
        assert "67108864" in json.dumps(paths["/profiles/{name}/calibration"]["post"]["responses"]["413"])
        assert "413" not in paths["/profiles/{name}"]["get"]["responses"]


def test_a_change_without_the_token_is_answered_before_its_body_is_sent(tmp_path: Path) -> None:
    """A client declares a 1 MB body and sends none of it: the 401 comes anyway (the body is never awaited)."""
    with running(make_settings(tmp_path), ready=False) as srv:
        port = srv.settings.http.port
        with socket.create_connection(("127.0.0.1", port), timeout=WAIT_S) as sock:
            head = (
                "PUT /profiles/big HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                f"Content-Length: {MIB - 1}\r\n\r\n"
            )
            sock.sendall(head.encode())
            reply = b""
            while b"\r\n\r\n" not in reply:  # bounded by the socket's timeout
                chunk = sock.recv(4096)
                if not chunk:
                    break
                reply += chunk
        assert reply.startswith(b"HTTP/1.1 401"), reply[:200]
