"""FastAPI dependencies: the running service and the bearer-token checks."""

from __future__ import annotations

import secrets
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.app import Service
from service.fleet import ProfileBank, UnknownProfile

#: The OpenAPI answer of a mutating route while the database does not accept writes.
STORAGE_UNAVAILABLE: dict[int | str, dict[str, Any]] = {
    503: {
        "description": "the database does not accept writes (storage degraded): nothing was changed, or, when the "
        "database failed during the request, the change is applied and queued (the detail says which)"
    }
}

_bearer = HTTPBearer(auto_error=False, description="the token of setting auth.token (or DATA_DIR/api-token)")


async def get_service(request: Request) -> Service:
    service: Service = request.app.state.service
    return service


ServiceDep = Annotated[Service, Depends(get_service)]


def profile_bank(service: Service, name: str) -> ProfileBank:
    """The profile's bank, or 404 naming the known profiles."""
    try:
        return service.engine.bank(name)
    except UnknownProfile as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc)) from exc


def token_problem(expected: str, scheme: str | None, token: str | None) -> tuple[str, str] | None:
    """Why a bearer token is refused, as (detail, WWW-Authenticate value), or None if it is the right one."""
    if scheme is None or token is None or scheme.lower() != "bearer":
        return "missing bearer token: send 'Authorization: Bearer TOKEN'", "Bearer"
    if not secrets.compare_digest(token.encode(), expected.encode()):
        return "invalid bearer token", 'Bearer error="invalid_token"'
    return None


def _check(service: Service, credentials: HTTPAuthorizationCredentials | None) -> str:
    scheme, token = (None, None) if credentials is None else (credentials.scheme, credentials.credentials)
    problem = token_problem(service.token, scheme, token)
    if problem is not None:
        detail, challenge = problem
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, detail=detail, headers={"WWW-Authenticate": challenge})
    return "operator"


async def require_token(
    service: ServiceDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
    """Mutating endpoints: a valid bearer token, always."""
    return _check(service, credentials)


async def require_read(
    service: ServiceDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> None:
    """Read endpoints: open unless setting auth.open_reads is false."""
    if not service.settings.auth.open_reads:
        _check(service, credentials)


Operator = Annotated[str, Depends(require_token)]
