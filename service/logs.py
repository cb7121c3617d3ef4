"""Structured (JSON lines) logging for the service's entry points; library code only calls logging."""

from __future__ import annotations

import json
import logging
import time

from linereg.io import jsonable


class JsonFormatter(logging.Formatter):
    """Formats a record as one JSON object: time, level, logger, message and its ``fields`` extra."""

    def format(self, record: logging.LogRecord) -> str:
        doc = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        doc.update(getattr(record, "fields", {}) or {})
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps({key: _plain(value) for key, value in doc.items()}, allow_nan=False)


def _plain(value: object) -> object:
    """Returns a field as JSON holds it: NaN and inf as null (as every JSON linereg writes), arrays as lists,
    anything else JSON has no type for as its text."""
    try:
        return jsonable(value)
    except TypeError:
        return str(value)


def configure(level: int = logging.INFO, json_lines: bool = True) -> None:
    """Sets up root logging for a service process (JSON lines on stderr, or plain text)."""
    handler = logging.StreamHandler()
    fmt = "%(asctime)s %(levelname)s %(name)s: %(message)s"
    handler.setFormatter(JsonFormatter() if json_lines else logging.Formatter(fmt))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
