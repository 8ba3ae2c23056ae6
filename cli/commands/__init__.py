"""One module per ``facecast`` sub-command; each defines ``register(subparsers)``.

Modules import nothing heavy at import time: the work is imported inside ``run``.
Modules named ``_…`` are not commands but helpers several commands share.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeAlias

if TYPE_CHECKING:
    import argparse

    #: What ``register`` is handed: ``facecast``'s sub-parsers (argparse's class is generic
    #: only in typeshed, so the alias exists for the type checker alone).
    Subparsers: TypeAlias = argparse._SubParsersAction[argparse.ArgumentParser]
