"""Structured logs: one JSON object per line on stderr, one line per event.

Call sites log an ``event`` name plus fields through ``extra=``; this module only formats
and wires handlers (for this process and, via ``uvicorn_log_config``, uvicorn's workers).
"""

from __future__ import annotations

import json
import logging
import re
import time
from typing import Any

__all__ = ["JsonFormatter", "uvicorn_log_config"]

# Attributes every LogRecord has; anything else came from ``extra=`` and is a field.
_STANDARD = set(logging.LogRecord("", 0, "", 0, "", (), None).__dict__.keys()) | {
    "message",
    "asctime",
    "color_message",
    "taskName",
}


# ``event`` is written first; ``websocket`` is a protocol object uvicorn attaches.
_DROPPED_FIELDS = {"event", "websocket"}


class _DropWebSocketChatter(logging.Filter):
    """uvicorn logs every WebSocket open/accept/close; our session.open/close say it once."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not (
            message in ("connection open", "connection closed")
            or message.endswith(('" [accepted]', '" 403'))
        )


#: uvicorn records about a client's own fault, by message: (our event name, why). uvicorn
#: logs them at error level with a traceback although it answered them correctly.
_CLIENT_FAULTS = {
    # websockets-sansio, on invalid UTF-8 in a text frame; it then closes with 1007 as
    # RFC 6455 §8.1 says (the legacy implementation does so without a word).
    "Invalid UTF-8 sequence received from client.": "ws.invalid_utf8",
}


class _DemoteClientFaults(logging.Filter):
    """Log what a client did wrong at info, without a traceback: it is not our failure."""

    def filter(self, record: logging.LogRecord) -> bool:
        event = _CLIENT_FAULTS.get(record.getMessage())
        if event is not None and record.levelno > logging.INFO:
            record.levelno, record.levelname = logging.INFO, "INFO"
            record.exc_info, record.exc_text = None, None
            record.event = event
        return True


class _RedactQueryTokens(logging.Filter):
    """Blank ``token=...`` in uvicorn's messages (they quote request paths with queries).

    PROTOCOL.md §2.2 allows ``?token=`` on WebSockets; whatever uvicorn says about such a
    connection (an error, a refusal) must not write the token into the logs.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "token=" in message:
            record.msg, record.args = _QUERY_TOKEN.sub(r"\1[redacted]", message), ()
        return True


_QUERY_TOKEN = re.compile(r"([?&]token=)[^&\s\"']*")


class JsonFormatter(logging.Formatter):
    """Format a record as one line of JSON: ts, level, logger, event, msg, fields."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
        }
        event = getattr(record, "event", None)
        entry["event"] = event or record.name
        entry["msg"] = record.getMessage()
        for key, value in record.__dict__.items():
            if key not in _STANDARD and key not in _DROPPED_FIELDS:
                entry[key] = value
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str, separators=(",", ":"))


def uvicorn_log_config(level: str) -> dict[str, Any]:
    """A ``logging.config`` dict routing uvicorn's and facecast's loggers to JSON on stderr.

    uvicorn's own access log is silenced: the app logs each request once itself.
    """
    level = level.upper()
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"json": {"()": JsonFormatter}},
        "filters": {
            "quiet_ws": {"()": _DropWebSocketChatter},
            "client_faults": {"()": _DemoteClientFaults},
            "no_tokens": {"()": _RedactQueryTokens},
        },
        "handlers": {
            "stderr": {
                "class": "logging.StreamHandler",
                "formatter": "json",
                "stream": "ext://sys.stderr",
            }
        },
        "loggers": {
            "uvicorn": {"handlers": ["stderr"], "level": level, "propagate": False},
            # On the logger, not the handler: every handler sees only what is left.
            "uvicorn.error": {
                "level": level,
                "filters": ["quiet_ws", "client_faults", "no_tokens"],
            },
            "uvicorn.access": {"handlers": [], "level": "WARNING", "propagate": False},
            "facecast": {"handlers": ["stderr"], "level": level, "propagate": False},
        },
    }
