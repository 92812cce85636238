"""Zenoh sessions as both sides open them: the configuration and the one transport error.

A session may start from a Zenoh JSON5 configuration file carrying TLS, mutual TLS, user/password authentication
and, on a router, an access-control list (docs/deployment.md). :func:`session_config` reads it and lays the
project's own choices on top, the :class:`ConfigValue` list each side builds (service.transport for the service,
edge_client.transport for the vehicles): mode and endpoints as without a file (a file that sets them too must
agree, or the session is refused naming both), the other values only where the file leaves Zenoh's default; the
user and password come from a separate file so that no secret sits in a configuration file.

The one module of agv_protocol that imports zenoh (agv_protocol.wire does not); service/transport.py and
edge_client/transport.py are the product's two others.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh


class TransportError(Exception):
    """Zenoh could not be configured, reached or used; the message names the endpoints or the file."""


@dataclass(frozen=True)
class ConfigValue:
    """A value the project sets in a session's Zenoh configuration.

    path : Zenoh's configuration path, such as 'connect/endpoints'; value : its JSON value; required : True
    when the value is the project's own (mode, endpoints): a configuration file may repeat it but not change
    it. False when it is only a default: a file that sets the path keeps its own value.
    """

    path: str
    value: Any
    required: bool = False


def read_credentials(credentials_file: str | Path) -> tuple[str, str]:
    """(user, password) from a file whose first line is ``USER:PASSWORD`` (a line of a Zenoh router's
    dictionary file); the error never shows the file's content."""
    try:
        lines = Path(credentials_file).read_text().splitlines()
    except OSError as exc:
        raise TransportError(f"zenoh credentials file {credentials_file}: cannot read: {exc.strerror}") from exc
    user, _, password = (lines[0].strip() if lines else "").partition(":")
    if not user or not password:
        raise TransportError(f"zenoh credentials file {credentials_file}: expected one line USER:PASSWORD")
    return user, password


def read_config_file(config_file: str | Path, credentials_file: str | Path | None = None) -> zenoh.Config:
    """A Zenoh configuration from a JSON5 file (Zenoh checks every key name), with the user and password of
    ``transport/auth/usrpwd`` from ``credentials_file`` when given (:func:`read_credentials`)."""
    try:
        config = zenoh.Config.from_file(str(config_file))
    except zenoh.ZError as exc:
        raise TransportError(f"zenoh configuration {config_file}: {_first_line(exc)}") from exc
    if credentials_file is not None:
        user, password = read_credentials(credentials_file)
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    return config


def apply_config_values(config: zenoh.Config, values: Sequence[ConfigValue], source: str) -> zenoh.Config:
    """Set each of ``values`` where ``config`` holds Zenoh's default; where it holds something else, keep
    it, unless the value is ``required`` and differs: then raise :class:`TransportError` naming both."""
    default = zenoh.Config()
    for item in values:
        current = json.loads(config.get_json(item.path))
        if current == json.loads(default.get_json(item.path)):
            try:
                config.insert_json5(item.path, json.dumps(item.value))
            except zenoh.ZError as exc:
                raise TransportError(f"invalid zenoh setting {item.path} = {item.value!r}: {_first_line(exc)}") from exc
        elif item.required and current != item.value:
            raise TransportError(
                f"{source} sets {item.path} = {json.dumps(current)}, but the settings say {json.dumps(item.value)}: "
                "set it in one place (mode and endpoints are settings; leave them out of the file)"
            )
    return config


def session_config(
    values: Sequence[ConfigValue], config_file: str | Path | None = None, credentials_file: str | Path | None = None
) -> zenoh.Config:
    """Zenoh's defaults (no file) or ``config_file``, with ``values`` applied (:func:`apply_config_values`)."""
    if config_file is None:
        if credentials_file is not None:
            raise TransportError("zenoh credentials need a configuration file (user/password goes over TLS)")
        config = zenoh.Config()
    else:
        config = read_config_file(config_file, credentials_file)
    return apply_config_values(config, values, f"zenoh configuration {config_file}")


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /", 1)[0].splitlines()[0] if text else type(exc).__name__
