"""One stream frame's clone: its weights (smoothed as the session asked) and vertices.

Pure computation on a rig and a frame, into buffers the session reuses, plus the cost
estimate that decides where it runs; no sockets, no session state but the filter.
"""

from __future__ import annotations

import numpy as np

from facecast.protocol import ErrorCode, Frame, Hello, ProtocolError, Smoothing
from facecast.rig import Rig
from facecast.rig.errors import InputError
from facecast.rig.filters import KalmanFilter, OneEuroFilter
from facecast.rig.kernel import to_float16

from .stages import CPU_CLOCK, StageTimes

__all__ = [
    "Outputs",
    "Smoother",
    "blend_seconds",
    "calibrated_filter",
    "clone_frame",
    "frame_error",
    "frame_weights",
    "smoothing_filter",
    "smoothing_name",
]

_RESULT_DTYPES = {"f32": np.float32, "f16": np.float16}
#: Cold-cache cost per vertex coordinate (this machine, one BLAS thread): a blend reads
#: the (M, 3V) float32 basis once, ~0.16 ns per multiply-add when it is not in cache, and
#: casting to f16 plus encoding and sending the result cost ~3 ns.
_SECONDS_PER_MAC = 0.16e-9
_SECONDS_PER_COORDINATE = 3e-9
#: The protocol error (§6.1) for each ``InputError`` code a rig raises about a frame.
_INPUT_ERRORS = {
    "out_of_range": ErrorCode.POINTS_OUT_OF_RANGE,
    "non_finite": ErrorCode.NON_FINITE,
    "wrong_point_count": ErrorCode.WRONG_POINT_COUNT,
}


def smoothing_name(smoothing: Smoothing, rig: Rig) -> str:
    """The filter ``smoothing`` runs on ``rig``, "kalman" or "one-euro" (``ready.smoothing``).

    ``smoothing.filter`` None is "auto" (PROTOCOL.md §5.1.1): the Kalman filter, which
    measured best (README "Temporal coherence"), where it can run (target "points" and a
    noise known, from ``smoothing.noise`` or ``rig``'s fit), else the one-euro filter.
    """
    if smoothing.filter is not None:
        return smoothing.filter
    return "kalman" if smoothing.target == "points" and _noise(smoothing, rig) > 0 else "one-euro"


def smoothing_filter(smoothing: Smoothing, rig: Rig) -> OneEuroFilter | KalmanFilter:
    """The filter a ``hello.smoothing`` asks for (PROTOCOL.md §5.1.1), for the session's rig.

    The filter is ``smoothing_name``'s. One-euro: the map's one-euro keys. Kalman:
    measurement noise ``smoothing.noise``, else the noise ``rig`` was fitted with; process
    noise ``smoothing.acceleration`` of those noise units per s^2.

    Raises
    ------
    ProtocolError
        INVALID_FIELD (fatal, as every refused ``hello``) for a Kalman filter named
        without a noise: no ``smoothing.noise`` and a rig fitted without one.
    """
    if smoothing_name(smoothing, rig) != "kalman":
        return OneEuroFilter(smoothing.min_cutoff, smoothing.beta, smoothing.d_cutoff)
    noise = _noise(smoothing, rig)
    if not noise > 0:
        raise ProtocolError(
            ErrorCode.INVALID_FIELD,
            "hello.options.smoothing.noise is needed for filter 'kalman': the rig was fitted "
            "without landmark noise",
            fatal=True,
        )
    return KalmanFilter(noise=noise, acceleration=smoothing.acceleration * noise)


def calibrated_filter(
    smoothing: Smoothing | None, rig: Rig, calibrated: Rig
) -> KalmanFilter | None:
    """The Kalman filter an auto smoothing runs once a calibrate with a ``noise`` has
    re-based ``rig`` noise-aware into ``calibrated`` (PROTOCOL.md §5.1.1, §5.2.5), or None
    where nothing changes.

    Auto (``smoothing.filter`` None) on points picks the Kalman filter where a noise is
    known; on a rig fitted exactly (a generic character) and without ``smoothing.noise``
    none is at the ``hello``, so it starts as the one-euro filter. The noise-aware re-base
    knows one: its σ (``fit_report["rebase"]["noise"]``: the largest of the calibrate's
    measured noise, the identity share and the rig's own, in the performer's units), which
    is the Kalman's. (At an acceleration given in σ units the filter's output does not
    depend on σ, only on one being known: a still camera's measured 0 does as well.) None:
    no smoothing, a filter named, target "weights", a noise known at the ``hello`` (the
    Kalman runs already), or an exact re-base (a calibrate without ``noise``).
    """
    if smoothing is None or smoothing.filter is not None or smoothing.target != "points":
        return None
    if _noise(smoothing, rig) > 0:
        return None
    rebase = calibrated.fit_report.get("rebase")
    sigma = float(rebase.get("noise", 0.0) or 0.0) if isinstance(rebase, dict) else 0.0
    if not sigma > 0:
        return None
    return KalmanFilter(noise=sigma, acceleration=smoothing.acceleration * sigma)


def _noise(smoothing: Smoothing, rig: Rig) -> float:
    """The Kalman's landmark noise: ``smoothing.noise``, else ``rig``'s fitted one (0: none)."""
    if smoothing.noise is not None:
        return smoothing.noise
    return float(rig.fit_report.get("noise", 0.0))


class Smoother:
    """A session's smoothing filter (PROTOCOL.md §5.1.1 ``smoothing``), clocked by ``frame.ts``.

    Used one frame at a time and in frame order, so needs no lock of its own: a
    session's on the event loop (weights are always computed there), a channel key's
    (``fanout``) under the key's lock.
    """

    def __init__(self, one_euro: OneEuroFilter | KalmanFilter, target: str) -> None:
        self.filter = one_euro
        self.target = target
        self.last_ts: float | None = None

    def __call__(self, values: np.ndarray, ts: float) -> np.ndarray:
        if self.last_ts is not None and ts < self.last_ts:
            # A client clock that jumped back (restart, wrap): start the filter afresh
            # rather than refusing every frame until ``ts`` catches up.
            self.filter.reset()
        self.last_ts = ts
        return self.filter(values.reshape(-1), ts).reshape(values.shape)


class Outputs:
    """A session's reused result buffers: (V, 3) float32 blend output, float16 wire copy.

    With output "moving" (PROTOCOL.md §5.2.1) they hold only the rig's N moving vertices
    and ``moving`` is True. Used by one clone at a time (the writer's), and each result
    is encoded (copied) before the next clone starts, so reuse is safe.
    """

    def __init__(self, hello: Hello, rig: Rig) -> None:
        self.dtype = _RESULT_DTYPES[hello.dtype]
        self.moving = hello.output == "moving"
        vertices = hello.output != "weights"
        # The result's array field: a moving session's N vertices travel in "vertices".
        self.name = "vertices" if vertices else "weights"
        rows = rig.moving_vertices.size if self.moving else rig.num_vertices
        self.rows = rows
        self.vertices = np.empty((rows, 3), np.float32) if vertices else None
        self.wire = np.empty((rows, 3), np.float16) if vertices and hello.dtype == "f16" else None


def frame_error(exc: InputError, seq: int | None, prefix: str = "frame") -> ProtocolError:
    """The non-fatal protocol error telling a client why its frame has no result."""
    code = _INPUT_ERRORS.get(exc.code, ErrorCode.INVALID_ARRAY)
    return ProtocolError(code, f"{prefix} cannot be cloned: {exc}", seq=seq)


def blend_seconds(num_vertices: int, num_examples: int) -> float:
    """Estimated cost of one vertices frame (blend, f16 cast, encode, send), seconds."""
    coordinates = 3 * num_vertices
    return coordinates * (num_examples * _SECONDS_PER_MAC + _SECONDS_PER_COORDINATE)


def frame_weights(rig: Rig, frame: Frame, hello: Hello, smoother: Smoother | None) -> np.ndarray:
    """The (M,) float64 weights of one frame, smoothed as the session asked."""
    points = frame.points
    if smoother is not None and smoother.target == "points":
        points = smoother(np.asarray(points, dtype=np.float64), frame.ts)
    weights = rig.weights(points, align=hello.align)
    if smoother is not None and smoother.target == "weights":
        weights = smoother(weights, frame.ts)
    return weights


def clone_frame(
    rig: Rig,
    frame: Frame,
    hello: Hello,
    smoother: Smoother | None,
    outputs: Outputs,
    stages: StageTimes | None = None,
) -> np.ndarray:
    """Weights (M,) or vertices (V, 3) of one frame, in the session's wire dtype.

    Vertices are written into ``outputs``' buffers and returned as one of them. With
    ``stages``, the time of the weights, blend and cast is added to it.
    """
    if stages is None:
        weights = frame_weights(rig, frame, hello, smoother)
        if outputs.vertices is None:
            return weights.astype(outputs.dtype)
        vertices = rig.blend(weights, out=outputs.vertices, moving=outputs.moving)
        return vertices if outputs.wire is None else to_float16(vertices, outputs.wire)
    clock = CPU_CLOCK
    started = clock()
    weights = frame_weights(rig, frame, hello, smoother)
    if outputs.vertices is None:
        values = weights.astype(outputs.dtype)
        stages.add("weights", clock() - started)
        return values
    blended = clock()
    vertices = rig.blend(weights, out=outputs.vertices, moving=outputs.moving)
    cast = clock()
    if outputs.wire is not None:
        vertices = to_float16(vertices, outputs.wire)
    stages.add("weights", blended - started)
    stages.add("blend", cast - blended)
    stages.add("cast", clock() - cast)
    return vertices
