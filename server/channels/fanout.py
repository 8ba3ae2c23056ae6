"""One channel frame cloned once per (rig, output, dtype) key and encoded once for all its watchers.

Runs in the clone worker threads, or on the loop for the microsecond keys (weights):
pure computation on a rig and a frame, returning bytes.
It holds no sockets, schedules nothing and knows nothing of who receives.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import msgpack
import numpy as np

from facecast.protocol import (
    Head,
    Result,
    Smoothing,
    Stamps,
    array_from_wire,
    array_to_wire,
    encode,
)
from facecast.protocol.arrays import check_result_finite
from facecast.protocol.fields import read_float
from facecast.rig.closure import check_contrast
from facecast.rig.errors import InputError, RigError
from facecast.rig.filters import OneEuroFilter
from facecast.rig.rebase import calibrate as calibrate_rig
from facecast.rig.sources.layouts import load_layout

from ..compute.cloning import Smoother

if TYPE_CHECKING:
    from facecast.rig import Rig

__all__ = ["ChannelFrame", "Key", "KeyState", "PointsKeyState", "key_state", "layout_first"]

log = logging.getLogger("facecast.server.channels")

#: (rig id, output, dtype): what a watcher asks for; watchers of one key share bytes.
Key = tuple[str, str, str]

_DTYPES = {"f32": np.float32, "f16": np.float16, "f64": np.float64}
#: The tracker layout: a watched rig of one of its earlier feature counts (20, 24 of 26)
#: takes the first of a frame's points.
_LAYOUT = load_layout()


def layout_first(points: np.ndarray, k: int) -> np.ndarray:
    """A frame's ``points`` (or its neutral, a blink) for a watched rig of ``k`` points.

    Unchanged, unless the frame has one of the tracker layout's feature counts and the rig
    an earlier, smaller one: then its first ``k`` (a layout's earlier version is its first
    points, in order; the /perform page sends such a rig the same, docs/perform.md). So a
    performer publishing the layout's 26 points drives viewers on 24- and 20-point
    characters too (PROTOCOL.md §2.4). Any other mismatch stays one, for the rig to refuse.
    """
    return points[:k] if _LAYOUT.takes_first(points.shape[0], k) else points


@dataclass(frozen=True)
class ChannelFrame:
    """A publisher's frame plus the channel options every key's clone needs.

    Small (K points), so it is what crosses processes through Redis (``to_bytes``).

    Attributes
    ----------
    seq, ts : the publisher's frame ``seq`` and ``ts``
    points : (K, 3) float16/32/64, as the publisher sent them (already point-smoothed)
    raw_points : (K, 3) or None, the frame's points before the publisher's point smoothing;
        None when ``points`` are those (no smoothing). What ``output=points`` watchers get.
    dropped : frames the publisher's session discarded so far (result.dropped)
    align, scale : the publisher's ``hello`` options, applied on every key's rig
    smoothing : the publisher's weight smoothing (target "weights"), or None
    neutral : (K, 3) or None, the performer's calibrated neutral
    neutral_noise : the landmark noise the neutral came with (calibrate ``noise``, §5.1.3):
        every key re-bases its rig noise-aware with it (``rig.rebase``); None: exactly
    neutral_blinks : {name: (K, 3)} or None, the performer's closed eyes the neutral came
        with (calibrate ``blinks``, §5.1.3): every key reads them as closed on its rig
    neutral_contrast : (low, high) or None, the performer's own curve for those blinks
        (calibrate ``blink_contrast``); None: the server's
    neutral_id : changes whenever ``neutral`` does (keys cache their calibrated rig by it)
    head : the frame's head pose (PROTOCOL.md §5.3), relayed unchanged in every key's result
    stamps : the frame's stage stamps as the server relays them (PROTOCOL.md §5.4: the
        publisher's plausible ones and ``server_in``), in every key's result of it; None:
        the publisher sent none
    """

    seq: int
    ts: float
    points: np.ndarray
    raw_points: np.ndarray | None = None
    dropped: int = 0
    align: bool = False
    scale: bool = False
    smoothing: Smoothing | None = None
    neutral: np.ndarray | None = None
    neutral_noise: float | None = None
    neutral_blinks: dict[str, np.ndarray] | None = None
    neutral_contrast: tuple[float, float] | None = None
    neutral_id: str = ""
    head: Head | None = None
    stamps: Stamps | None = None

    def to_bytes(self) -> bytes:
        data: bytes = msgpack.packb(
            {
                "seq": self.seq,
                "ts": self.ts,
                "points": array_to_wire(self.points),
                "raw_points": None if self.raw_points is None else array_to_wire(self.raw_points),
                "dropped": self.dropped,
                "align": self.align,
                "scale": self.scale,
                "smoothing": None if self.smoothing is None else self.smoothing.serialize(),
                "neutral": None if self.neutral is None else array_to_wire(self.neutral),
                "neutral_noise": self.neutral_noise,
                "neutral_blinks": None
                if self.neutral_blinks is None
                else {name: array_to_wire(a) for name, a in self.neutral_blinks.items()},
                "neutral_contrast": None
                if self.neutral_contrast is None
                else list(self.neutral_contrast),
                "neutral_id": self.neutral_id,
                "head": None if self.head is None else self.head.serialize(),
                "stamps": None if self.stamps is None else self.stamps.serialize(),
            },
            use_bin_type=True,
        )
        return data

    @classmethod
    def from_bytes(cls, data: bytes, max_points: int) -> ChannelFrame:
        """Parse what ``to_bytes`` wrote; raises ``ValueError`` (or ProtocolError) if malformed."""
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=1 << 24)
        if not isinstance(obj, dict):
            raise ValueError("channel frame: not a map")
        neutral = obj.get("neutral")
        blinks = obj.get("neutral_blinks")
        if blinks is not None and (not isinstance(blinks, dict) or len(blinks) > 2):
            raise ValueError("channel frame: neutral_blinks is not a map of at most 2 arrays")
        contrast = obj.get("neutral_contrast")
        if contrast is not None:
            contrast = check_contrast(contrast)  # InputError, a ValueError, if not a curve
        raw = obj.get("raw_points")
        smoothing = obj.get("smoothing")
        head = obj.get("head")
        stamps = obj.get("stamps")
        return cls(
            seq=int(obj["seq"]),
            ts=float(obj["ts"]),
            points=array_from_wire(obj["points"], "points", trailing=(3,), max_rows=max_points),
            raw_points=None
            if raw is None
            else array_from_wire(raw, "raw_points", trailing=(3,), max_rows=max_points),
            dropped=int(obj.get("dropped", 0)),
            align=bool(obj.get("align", False)),
            scale=bool(obj.get("scale", False)),
            smoothing=None if smoothing is None else Smoothing.parse(smoothing),
            neutral=None
            if neutral is None
            else array_from_wire(neutral, "neutral", trailing=(3,), max_rows=max_points),
            neutral_noise=read_float(obj, "neutral_noise", "channel frame neutral_noise", None),
            neutral_blinks=None
            if blinks is None
            else {
                str(name): array_from_wire(a, "neutral_blinks", trailing=(3,), max_rows=max_points)
                for name, a in blinks.items()
            },
            neutral_contrast=contrast,
            neutral_id=str(obj.get("neutral_id", "")),
            head=None if head is None else Head.parse(head, "head"),
            stamps=None if stamps is None else Stamps.parse(stamps, "stamps"),
        )


class _Key:
    """What every key's pipeline keeps: its watchers' newest result and how it was made."""

    #: Whether ``clone`` evaluates a rig (counted in the channel's ``clones``).
    CLONES = True

    def __init__(self, key: Key, rig: Rig) -> None:
        self.key = key
        self.rig = rig
        self.rig_id, self.output, self.dtype = key
        self.clones = 0
        #: (M,) float64 weights of the newest clone, the pose a lost face eases from.
        self.last_weights: np.ndarray | None = None
        #: Encoded newest result: what a late joiner of this key gets at once.
        self.last_bytes: bytes | None = None
        self.last_seq = -1
        #: The last frame could not be cloned for this key (logged once per streak).
        self.failing = False
        self._lock = threading.Lock()

    def inline(self, frame: ChannelFrame) -> bool:
        """Whether ``clone(frame)`` costs microseconds, so runs on the event loop itself.

        Weights (no blend) from a rig already derived for the frame's calibration: a
        clone thread's round trip costs the loop more (~30 µs) than such a clone.
        """
        return False

    def _keep(self, data: bytes, seq: int, count: bool) -> None:
        """Count a clone and keep ``data`` as the newest result (the lock held)."""
        if count:
            self.clones += 1
        if seq >= self.last_seq or not count:
            self.last_bytes, self.last_seq = data, seq


class KeyState(_Key):
    """The clone pipeline of one key in one process: rig, calibration, filter, last pose.

    ``clone`` and ``ease`` may be called from any clone thread; a lock keeps one frame
    at a time per key (the filter and the last pose are per key state).
    """

    def __init__(self, key: Key, rig: Rig) -> None:
        super().__init__(key, rig)
        self._rig_for: tuple[str, bool] = ("", False)
        self._effective = rig
        self._smoothing: Smoothing | None = None
        self._smoother: Smoother | None = None

    def inline(self, frame: ChannelFrame) -> bool:
        # A new calibration neutral refits the projection (ms): that goes to a thread.
        wanted = (frame.neutral_id if frame.neutral is not None else "", frame.scale)
        return self.output == "weights" and wanted == self._rig_for

    def _rig(self, frame: ChannelFrame) -> Rig:
        wanted = (frame.neutral_id if frame.neutral is not None else "", frame.scale)
        if wanted != self._rig_for:
            rig = self.rig
            if frame.neutral is not None:
                k = rig.num_points
                blinks = frame.neutral_blinks
                if blinks is not None:
                    blinks = {name: layout_first(b, k) for name, b in blinks.items()}
                try:
                    rig = calibrate_rig(
                        rig, layout_first(frame.neutral, k), frame.neutral_noise, blinks,
                        frame.neutral_contrast,
                    )  # fmt: skip
                except RigError as exc:
                    # The publisher's rig accepted this neutral; this one cannot: serve it
                    # uncalibrated rather than not at all.
                    log.warning(
                        "calibration does not apply to this rig",
                        extra={"event": "channel.calibration_skipped", "rig": self.rig_id,
                               "error": str(exc)},
                    )  # fmt: skip
            if frame.scale:
                # A rig of its own: the store's cached rig, shared by every key and session,
                # stays as it is.
                rig = rig.with_align_scale(True)
            self._effective, self._rig_for = rig, wanted
        return self._effective

    def _smooth(self, weights: np.ndarray, frame: ChannelFrame) -> np.ndarray:
        if frame.smoothing is None:
            self._smoother = None
            return weights
        if self._smoother is None or frame.smoothing != self._smoothing:
            sm = frame.smoothing
            one_euro = OneEuroFilter(min_cutoff=sm.min_cutoff, beta=sm.beta, d_cutoff=sm.d_cutoff)
            self._smoother, self._smoothing = Smoother(one_euro, "weights"), sm
        return self._smoother(weights, frame.ts)

    def clone(self, frame: ChannelFrame, arrived: float, *, count: bool = True) -> bytes:
        """The encoded result of ``frame`` for this key (runs in a clone thread).

        ``arrived`` is the ``perf_counter`` when the frame reached this process (for
        ``proc_us``); ``count`` is False for a late joiner's catch-up clone.

        Raises ``InputError`` (RigError) when the points cannot be evaluated, and
        ``ProtocolError`` (RESULT_NOT_FINITE) when the result overflows this key's dtype.
        """
        with self._lock:
            rig = self._rig(frame)
            points = layout_first(frame.points, rig.num_points)
            weights = np.asarray(rig.weights(points, align=frame.align), dtype=np.float64)
            weights = self._smooth(weights, frame)
            self.last_weights = weights
            data = self._encode(
                rig, weights, frame.seq, frame.ts, frame.dropped, arrived, frame.head,
                # A late joiner's catch-up is no live frame: its age is not the path's.
                frame.stamps if count else None,
            )  # fmt: skip
            self._keep(data, frame.seq, count)
            return data

    def ease(self, alpha: float, seq: int, ts: float, dropped: int) -> bytes | None:
        """The last pose blended ``alpha`` (0..1) of the way to the neutral, encoded.

        Weights mode blends towards the one-hot neutral ``(1, 0, ..., 0)``; vertices mode
        blends those weights, so it moves towards the target's neutral mesh. None when
        this key has never cloned a frame.
        """
        with self._lock:
            if self.last_weights is None:
                return None
            neutral = np.zeros_like(self.last_weights)
            neutral[0] = 1.0
            weights = (1.0 - alpha) * self.last_weights + alpha * neutral
            data = self._encode(self._effective, weights, seq, ts, dropped, time.perf_counter())
            self.last_bytes = data
            return data

    def _encode(
        self,
        rig: Rig,
        weights: np.ndarray,
        seq: int,
        ts: float,
        dropped: int,
        arrived: float,
        head: Head | None = None,
        stamps: Stamps | None = None,
    ) -> bytes:
        dtype = _DTYPES[self.dtype]
        # An overflow to infinity is caught below, as RESULT_NOT_FINITE, not warned about.
        with np.errstate(over="ignore"):
            if self.output == "weights":
                values = weights.astype(dtype)
            else:
                vertices = rig.blend(weights)
                values = vertices if dtype is np.float32 else vertices.astype(dtype)
        check_result_finite(values, f"result.{self.output}", seq)
        result = Result(
            seq=seq,
            ts=ts,
            weights=values if self.output == "weights" else None,
            vertices=values if self.output == "vertices" else None,
            proc_us=max(0, int((time.perf_counter() - arrived) * 1e6)),
            dropped=dropped,
            server_ts=time.time(),
            head=head,  # eased results (no frame) carry none: the receiver keeps the last
            stamps=stamps,  # nor stamps: they are not a frame's
        )
        return encode(result)


class PointsKeyState(_Key):
    """The ``output=points`` key (PROTOCOL.md §2.4): the published frame itself, encoded once.

    Same interface as `KeyState` for the channel's pump, but no rig is evaluated: the
    rig only fixes K (``layout_first``; a frame with another K raises ``InputError``,
    reported to this key's watchers like any rig mismatch). A lost face is not eased:
    there is no frame to invent, so ``ease`` gives nothing.
    """

    CLONES = False

    def inline(self, frame: ChannelFrame) -> bool:
        return True  # K points cast and encoded: microseconds

    def clone(self, frame: ChannelFrame, arrived: float, *, count: bool = True) -> bytes:
        """The encoded ``points`` result of ``frame``: its raw points in this key's dtype."""
        points = frame.points if frame.raw_points is None else frame.raw_points
        points = layout_first(points, self.rig.num_points)
        if points.shape[0] != self.rig.num_points:
            raise InputError(
                f"frame has {points.shape[0]} points, rig {self.rig_id!r} has K="
                f"{self.rig.num_points}",
                code="wrong_point_count",
            )
        values = np.asarray(points, dtype=_DTYPES[self.dtype])
        check_result_finite(values, "result.points", frame.seq)  # f64 beyond f32's range
        result = Result(
            seq=frame.seq,
            ts=frame.ts,
            points=values,
            proc_us=max(0, int((time.perf_counter() - arrived) * 1e6)),
            dropped=frame.dropped,
            server_ts=time.time(),
            head=frame.head,
            stamps=frame.stamps if count else None,
        )
        data = encode(result)
        with self._lock:
            self._keep(data, frame.seq, count)
        return data

    def ease(self, alpha: float, seq: int, ts: float, dropped: int) -> bytes | None:
        return None


def key_state(key: Key, rig: Rig) -> KeyState | PointsKeyState:
    """The pipeline of a watched ``key``: a clone on ``rig``, or the frames themselves."""
    return PointsKeyState(key, rig) if key[1] == "points" else KeyState(key, rig)
