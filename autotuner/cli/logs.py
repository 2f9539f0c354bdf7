"""The daemon's log: one line per record on stderr, with a UTC timestamp, as text or as JSON, secrets masked.

``autotuner serve --log-level LEVEL --log-format text|json`` calls :func:`setup`.
uvicorn's own loggers propagate to the same handler (it is started with
``log_config=None``), so its access and error lines have the same form.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Iterable
from datetime import UTC, datetime

# Libraries whose INFO records are protocol detail (asyncua logs every session and subscription): their
# WARNING and up only, whatever --log-level says (their debug output would drown the daemon's own lines).
CHATTY = ("asyncua", "pymodbus", "can")



def _timestamp(record: logging.LogRecord) -> str:
    return datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class TextFormatter(logging.Formatter):
    """``2026-12-01T21:00:00.123Z WARNING autotuner.service.daemon: message`` (and the traceback, if any)."""

    def format(self, record: logging.LogRecord) -> str:
        line = f"{_timestamp(record)} {record.levelname} {record.name}: {record.getMessage()}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time (UTC ISO 8601), level, logger, message, and exception when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {"time": _timestamp(record), "level": record.levelname, "logger": record.name,
                 "message": record.getMessage()}
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False)


class Masking(logging.Filter):
    """Replaces each of ``secrets`` by ``***`` in every record's message (a database password, ...)."""

    def __init__(self, secrets: Iterable[str]) -> None:
        super().__init__()
        self.secrets = [s for s in secrets if s]

    def filter(self, record: logging.LogRecord) -> bool:
        if self.secrets:
            message = record.getMessage()
            for secret in self.secrets:
                message = message.replace(secret, "***")
            record.msg, record.args = message, None
        return True


def setup(level: str = "info", form: str = "text", secrets: Iterable[str] = ()) -> logging.Handler:
    """Send every logger's records at ``level`` and above to stderr in ``form``; the handler installed."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if form == "json" else TextFormatter())
    handler.addFilter(Masking(secrets))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in CHATTY:  # their INFO is protocol detail; the daemon's own INFO lines stay readable
        logging.getLogger(name).setLevel(max(logging.WARNING, root.level))
    logging.captureWarnings(True)
    return handler
