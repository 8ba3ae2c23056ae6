"""The names the server hands out and checks: rig ids, performer names, ``{id}@{performer}``.

Pure string rules shared by the rig store, the performer routes and the token settings
(a token may be bound to performer names); no I/O and no imports from the server here.
"""

from __future__ import annotations

import re

__all__ = [
    "NAME_PATTERN",
    "PERFORMER_SEPARATOR",
    "RIG_ID_PATTERN",
    "performer_rig_id",
    "valid_name",
    "valid_rig_id",
]

_NAME_BODY = r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}"
#: A plain rig id, and a performer's name.
NAME_PATTERN = f"^{_NAME_BODY}$"
#: Joins a character's rig id and a performer's name into the id of the rig fitted on that
#: performer's own expressions (``ict@alice``; see server/SERVER.md, "Performers").
PERFORMER_SEPARATOR = "@"
RIG_ID_PATTERN = f"^{_NAME_BODY}({PERFORMER_SEPARATOR}{_NAME_BODY})?$"
_RIG_ID = re.compile(RIG_ID_PATTERN)
_NAME = re.compile(NAME_PATTERN)


def valid_rig_id(rig_id: str) -> bool:
    """A plain id (``ict``) or a performer rig's (``ict@alice``)."""
    # fullmatch: ``$`` alone would accept a trailing newline.
    return _RIG_ID.fullmatch(rig_id) is not None


def valid_name(name: str) -> bool:
    """A plain rig id or a performer's name: no separator."""
    return _NAME.fullmatch(name) is not None


def performer_rig_id(rig_id: str, performer: str) -> str:
    """The id of ``rig_id`` refitted on ``performer``'s expressions (both plain names)."""
    if not (valid_name(rig_id) and valid_name(performer)):
        raise ValueError(f"not plain names: {rig_id!r}, {performer!r}")
    return f"{rig_id}{PERFORMER_SEPARATOR}{performer}"
