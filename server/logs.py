"""Structured logs: one JSON object per line on stderr, one line per event.

Call sites log an ``event`` name plus fields through ``extra=``; this module formats and
wires handlers (for this process and, via ``uvicorn_log_config``, uvicorn's workers), and
keeps refusals a client controls to one line per streak (``RefusalLog``).
"""

from __future__ import annotations

import json
import logging
import re
import time
from typing import Any

__all__ = ["STREAK_GAP", "STREAK_REPORT", "JsonFormatter", "RefusalLog", "uvicorn_log_config"]

#: A streak of refusals of one code ends after this many seconds without one.
STREAK_GAP = 10.0
#: While a streak lasts, its count is logged at most this often.
STREAK_REPORT = 60.0


class RefusalLog:
    """Logs refusals once per streak: the first of each code, then counts.

    A client decides how often it is refused; one line per refusal would be a log flood
    it controls. The first refusal of a code logs a line at info (``event``, the code,
    the caller's fields); later ones less than ``STREAK_GAP`` s after the previous are
    only counted, and the count (``suppressed``: refusals of this code not logged since
    the last line) goes out with the next line: the one starting the next streak, or the
    one logged every ``STREAK_REPORT`` s while a streak goes on. The clock is passed in.
    """

    def __init__(self, logger: logging.Logger, event: str, message: str) -> None:
        self.logger = logger
        self.event = event
        self.message = message
        # code -> [time of the last refusal, of the last line, refusals since that line]
        self._streaks: dict[str, list[float]] = {}

    def refused(self, code: str, now: float, **fields: Any) -> bool:
        """Count a refusal at ``now``; True if it was logged."""
        streak = self._streaks.get(code)
        if streak is not None and now - streak[0] < STREAK_GAP and now - streak[1] < STREAK_REPORT:
            streak[0] = now
            streak[2] += 1
            return False
        suppressed = 0 if streak is None else int(streak[2])
        self._streaks[code] = [now, now, 0]
        self.logger.info(
            self.message,
            extra={"event": self.event, "code": code, "suppressed": suppressed, **fields},
        )
        return True


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
