"""What the API refuses before it reads a body: one too large (413), and a change without the token (401).

A pure ASGI middleware, so that nothing is buffered before the checks: a body
whose ``Content-Length`` passes the limit is refused unread, and a chunked one
is counted while the application reads it and refused when it passes the
limit. A mutating request (POST, PUT, PATCH, DELETE) without the right bearer
token is refused before its body is read, with the answer the route's own
check gives. Validation errors (422) echo at most ``MAX_ECHO_CHARS`` of an
input, never a whole body.
"""

from __future__ import annotations

import json
import re
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from fastapi import FastAPI, Request, status
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from service.api.deps import token_problem
from service.settings import HttpSettings

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: The longest input a 422 answer repeats, in characters of its JSON.
MAX_ECHO_CHARS = 200
MUTATING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
CALIBRATION_PATH = re.compile(r"^/profiles/[^/]+/calibration$")


class BodyTooLarge(HTTPException):
    """The body passed the limit while it was read (raised from ``receive``: FastAPI passes HTTPException on)."""

    def __init__(self, limit: int) -> None:
        super().__init__(status.HTTP_413_CONTENT_TOO_LARGE, detail=f"the request body is larger than {limit} bytes")


class RequestGate:
    """413 for a body over the route's limit, 401 for a change without the token: both before the body is read."""

    def __init__(self, app: ASGIApp, http: HttpSettings) -> None:
        self.app = app
        self.http = http

    def limit(self, path: str) -> int:
        if CALIBRATION_PATH.match(path):
            return self.http.max_calibration_body_bytes
        return self.http.max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit(scope["path"])
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        declared = headers.get("content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            await _answer(send, status.HTTP_413_CONTENT_TOO_LARGE, f"the request body is larger than {limit} bytes")
            return
        if scope["method"] in MUTATING:
            refused = self._unauthorised(scope, headers.get("authorization"))
            if refused is not None:
                detail, challenge = refused
                await _answer(send, status.HTTP_401_UNAUTHORIZED, detail, {"WWW-Authenticate": challenge})
                return
        started = False
        received = 0

        async def counted_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise BodyTooLarge(limit)
            return message

        async def tracked_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted_receive, tracked_send)
        except BodyTooLarge as exc:  # read outside a route (a middleware): answer here if nothing was sent
            if started:
                raise
            await _answer(send, exc.status_code, str(exc.detail))

    @staticmethod
    def _unauthorised(scope: Scope, authorization: str | None) -> tuple[str, str] | None:
        service = getattr(scope["app"].state, "service", None)
        if service is None:
            return None  # not started: the route answers
        scheme, _, token = (authorization or "").partition(" ")
        return token_problem(service.token, scheme or None, token.strip() or None)


async def _answer(send: Send, code: int, detail: str, headers: dict[str, str] | None = None) -> None:
    body = json.dumps({"detail": detail}).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    # the body is not read: close the connection rather than leave the client's bytes in it
    raw.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": code, "headers": raw})
    await send({"type": "http.response.body", "body": body})


def _short(value: Any) -> Any:
    """An input as a 422 repeats it: itself if its JSON is short, else its beginning and its length."""
    text = json.dumps(jsonable_encoder(value))
    if len(text) <= MAX_ECHO_CHARS:
        return value
    return f"{text[:MAX_ECHO_CHARS]}... ({len(text)} characters, not repeated)"


async def validation_error(request: Request, exc: Exception) -> JSONResponse:
    """FastAPI's 422 answer, with every long input shortened (a large body is never echoed)."""
    errors = exc.errors() if isinstance(exc, RequestValidationError) else []
    shortened = [{**e, "input": _short(e["input"])} if "input" in e else e for e in errors]
    return JSONResponse({"detail": jsonable_encoder(shortened)}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)


def document_413(app: FastAPI, http: HttpSettings) -> None:
    """Add the 413 and 400 answers to every operation with a request body in the OpenAPI document, and document a
    422's detail as what it is: the list of field errors, or one sentence."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()
        for path, operations in schema.get("paths", {}).items():
            for operation in operations.values():
                if isinstance(operation, dict) and "requestBody" in operation:
                    limit = http.max_calibration_body_bytes if CALIBRATION_PATH.match(path) else http.max_body_bytes
                    responses = operation.setdefault("responses", {})
                    responses["413"] = {
                        "description": f"the body is larger than {limit} bytes (settings http.max_body_bytes, "
                        "http.max_calibration_body_bytes); refused before it is read"
                    }
                    responses["400"] = {
                        "description": "the body is not valid JSON (the detail says so)",
                        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/HTTPError"}}},
                    }
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components["HTTPError"] = {
            "title": "HTTPError",
            "type": "object",
            "properties": {"detail": {"type": "string", "title": "Detail"}},
            "required": ["detail"],
        }
        # a 422 names the fields at fault (a list, FastAPI's validation errors) or says in a sentence what a
        # valid request needs that no field's type can say (a refused calibration, an unknown level filter...)
        validation = components.get("HTTPValidationError")
        if validation is not None:
            detail = validation["properties"]["detail"]
            validation["properties"]["detail"] = {
                "title": "Detail",
                "anyOf": [{k: v for k, v in detail.items() if k != "title"}, {"type": "string"}],
            }
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
