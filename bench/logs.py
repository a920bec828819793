"""Service logging: plain text (default) or JSON lines (``--log-format json`` / ``BENCH_LOG_FORMAT=json``).

A JSON line holds ``ts`` (UTC, ISO 8601 with milliseconds), ``level``, ``logger``, ``message``, the
exception text under ``exc`` when there is one, and any ``extra={...}`` fields a call passed.
"""
from __future__ import annotations

import datetime as dt
import json
import logging

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime", "color_message"}


class JsonLinesFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        doc = {"ts": dt.datetime.fromtimestamp(record.created, dt.timezone.utc).isoformat(timespec="milliseconds")
                     .replace("+00:00", "Z"),
               "level": record.levelname, "logger": record.name, "message": record.getMessage()}
        for key, value in vars(record).items():
            if key not in _STANDARD and not key.startswith("_"):
                doc[key] = value
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str, ensure_ascii=False)


def configure_logging(level: str = "info", fmt: str | None = None) -> str:
    """Set up the root logger; ``fmt`` None = ``BENCH_LOG_FORMAT``.  Returns the format used."""
    if fmt is None:
        from bench.settings import load_settings
        fmt = load_settings().log_format
    if fmt not in ("text", "json"):
        raise ValueError(f"log format {fmt!r}: use text or json")
    handler = logging.StreamHandler()
    handler.setFormatter(JsonLinesFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level.upper())
    return fmt


def uvicorn_log_config(fmt: str) -> dict | None:
    """uvicorn's ``log_config``: its own (text) configuration, or None in JSON mode so its loggers go
    through the root handler set by ``configure_logging``."""
    if fmt == "json":
        return None
    from uvicorn.config import LOGGING_CONFIG
    return LOGGING_CONFIG
