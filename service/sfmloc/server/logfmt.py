"""Structured log lines. Library code calls ``event(log, level, "name", key=value, ...)``; the
entry point (``sfmloc serve``, a worker process) picks the format with ``setup_logging``:

``kv`` (default), one line per event (shown here on two)::

    ts=2026-11-21T06:30:00.123Z level=info logger=sfmloc.server.sessions
    event=session_open map=lab client=drone1 worker=0

``json``: one object per line, ``{"ts", "level", "logger", "event" | "msg", ...fields}``.
Plain log calls (``log.info("...")``) appear as ``msg="..."``.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any


def _quote(v: Any) -> str:
    s = (
        v
        if isinstance(v, str)
        else (json.dumps(v) if isinstance(v, (list, dict, bool)) or v is None else str(v))
    )
    if s == "" or any(c in s for c in ' "=\n\t'):
        return json.dumps(s)
    return s


def kv(**fields: Any) -> str:
    return " ".join(f"{k}={_quote(v)}" for k, v in fields.items())


def event(logger: logging.Logger, level: int, name: str, **fields: Any) -> None:
    """Log an event with fields (readable as ``name k=v ...`` with any formatter)."""
    if logger.isEnabledFor(level):
        logger.log(level, "%s %s", name, kv(**fields), extra={"event": name, "fields": fields})


def _ts(record: logging.LogRecord) -> str:
    return (
        time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        + f".{int(record.msecs):03d}Z"
    )


class KeyValueFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        head = f"ts={_ts(record)} level={record.levelname.lower()} logger={record.name}"
        if hasattr(record, "event"):
            fields: dict[str, Any] = getattr(record, "fields", {})  # set by event() through extra=
            line = f"{head} event={_quote(record.event)} {kv(**fields)}".rstrip()
        else:
            line = f"{head} msg={_quote(record.getMessage())}"
        if record.exc_info:
            line += " exc=" + _quote(self.formatException(record.exc_info))
        return line


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        d: dict[str, Any] = {
            "ts": _ts(record),
            "level": record.levelname.lower(),
            "logger": record.name,
        }
        if hasattr(record, "event"):
            d["event"] = record.event
            d.update(
                {
                    k: v
                    if isinstance(v, (int, float, str, bool, list, dict)) or v is None
                    else str(v)
                    for k, v in getattr(record, "fields", {}).items()
                }
            )
        else:
            d["msg"] = record.getMessage()
        if record.exc_info:
            d["exc"] = self.formatException(record.exc_info)
        return json.dumps(d)


def setup_logging(fmt: str = "kv", level: int = logging.INFO) -> None:
    """Entry points only: route the root logger to stderr in ``fmt`` ("kv" or "json")."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else KeyValueFormatter())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level)
    if level > logging.DEBUG:
        for noisy in ("faiss.loader", "zenoh", "grpc"):  # start-up chatter, not events
            logging.getLogger(noisy).setLevel(logging.WARNING)
