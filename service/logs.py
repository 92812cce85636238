"""Structured logs: every alarm transition and job outcome as an event, and an optional JSON line format.

:func:`event` writes one record on the ``agv_fe.events`` logger: a readable message (``alarm raised
vehicle=truck-7 kind=torque_fault level=WARN ...``) and the fields themselves on the record. With
``agv-fe serve --log-format json`` every record, the service's, the events and uvicorn's access log alike,
is one JSON object per line (:class:`JsonFormatter`): ``t`` (UTC, ISO 8601), ``severity``, ``logger``,
``message``, and for an event ``event`` and its fields (an alarm's ``level`` is its alarm level).
"""

from __future__ import annotations

import json
import logging
import time
from typing import Any

EVENTS = logging.getLogger("agv_fe.events")
#: the attributes every LogRecord has: what is left on a record was passed in ``extra``
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}


def event(name: str, severity: int = logging.INFO, /, **fields: Any) -> None:
    """Log one event ``name`` (alarm, job) at ``severity`` with its ``fields`` (which may be called kind or level:
    the first two parameters are positional only); fields that are None are left out."""
    present = {k: v for k, v in fields.items() if v is not None}
    text = " ".join(f"{k}={v}" for k, v in present.items())
    EVENTS.log(severity, "%s %s", name, text, extra={"event": name, "fields": present})


class JsonFormatter(logging.Formatter):
    """One JSON object per record: t, severity, logger, message, the event and its fields (never over those four),
    and the exception."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "t": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "severity": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        kind = getattr(record, "event", None)
        if kind is not None:
            fields = getattr(record, "fields", {})
            out.update({k: v for k, v in fields.items() if k not in out})
            out["event"] = kind
        else:  # other extras (uvicorn's access log passes none; a caller may)
            out.update({k: v for k, v in vars(record).items() if k not in _STANDARD})
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def configure(level: str, fmt: str = "text") -> None:
    """The process's logging: one handler on the root logger, text or JSON; uvicorn's loggers (its access log
    too) hand their records to it instead of printing in their own format."""
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        logger = logging.getLogger(name)
        logger.handlers.clear()
        logger.propagate = True
