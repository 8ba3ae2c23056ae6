"""Which skips CI must not take: a test that skips for want of ICT-FaceKit fails under
CI=true (CI has ../shared beside its checkout, so its absence is a bug); elsewhere (a
newcomer's machine without it) it skips, as README's test command says."""

from __future__ import annotations

from collections.abc import Mapping

#: Words in a skip's reason that name ICT-FaceKit's data (every ICT skip in the suite says one).
ICT_WORDS = ("ict-facekit", "facecast_ict")


def fails_on_ci(reason: str, environ: Mapping[str, str]) -> str | None:
    """The failure message for a skip CI must not take (its ``reason`` names ICT-FaceKit's
    data), or None to let it skip. Judged by the reason alone: a test marked ``ict`` that
    skips for another cause is not this rule's business."""
    if environ.get("CI") != "true":
        return None
    if any(word in reason.lower() for word in ICT_WORDS):
        return f"CI=true needs ICT-FaceKit (../shared/data/ict-facekit), but the test skipped: {reason}"
    return None
