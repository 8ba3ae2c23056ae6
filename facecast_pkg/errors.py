"""The root of every exception facecast raises on purpose, and how its codes are named.

Only the root lives here (no I/O, no imports); each package's exceptions module draws its
own branch. The tree::

    FacecastError                    code: str, one per class, never reused or renamed
    ├── ProtocolError(ValueError)    facecast.protocol.errors; code: the numeric ErrorCode
    │                                of the wire (PROTOCOL.md §6) instead of a string
    ├── RigError                     facecast.rig.errors: the engine (bad examples, fit, rig files)
    ├── server errors                facecast.server.errors draws them: HTTP problems,
    │                                settings, the rig store, archives, the channel bus
    ├── ClientError                  facecast.client.errors: connecting, REST look-ups
    └── CLI errors                   facecast.cli.errors: commands, the renderer, the tracker

A class's ``code`` is its default; an instance may carry a finer code of the same family
(``RigError(message, code="bad_view")``, an HTTP problem's ``code``). Catching
``FacecastError`` catches every one of them; ``except`` on a concrete class, or on the
built-in it also derives from (``ValueError``, ``ConnectionError``, ``LookupError``),
behaves as it did before this root existed.
"""

from __future__ import annotations

__all__ = ["FacecastError"]


class FacecastError(Exception):
    """Base of facecast's exceptions; ``code`` is a stable machine-readable name.

    Subclasses set ``code`` in their body (a string distinct from every other class's);
    `facecast.protocol.errors.ProtocolError` is the one exception, whose instances carry
    the wire's numeric code.
    """

    #: str for every class but ProtocolError, whose instances hold an int (ErrorCode).
    code: str | int = "facecast_error"
