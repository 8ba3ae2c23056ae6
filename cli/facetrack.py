"""Camera or video frames -> feature points, through MediaPipe's legacy FaceMesh and a layout.

Needs the optional extra ``facecast[perform]``: mediapipe 0.10.21, whose wheel ships the
FaceMesh models (later versions do not), and OpenCV. It reads and tracks frames; it never
publishes and never fetches anything (the models load from the installed wheel).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from facecast.cli.errors import TrackerUnavailable
from facecast.cli.eyelids import EyelidModel
from facecast.rig.errors import InputError
from facecast.rig.sources.facemesh import image_to_mesh, normalise_mesh
from facecast.rig.sources.layouts import Layout, load_layout

__all__ = ["FaceTracker", "Tracked", "TrackerUnavailable", "VideoSource"]

#: The extra that brings the tracker, for messages.
EXTRA = "facecast[perform]"


def _modules() -> tuple[ModuleType, ModuleType]:
    """OpenCV and MediaPipe's FaceMesh (the `perform` extra), or TrackerUnavailable."""
    try:
        import cv2
        from mediapipe.python.solutions import face_mesh
    except ImportError as exc:
        raise TrackerUnavailable(
            f"facecast perform needs mediapipe 0.10.21 and OpenCV: pip install '{EXTRA}' ({exc})"
        ) from None
    return cv2, face_mesh


@dataclass(frozen=True, eq=False)
class Tracked:
    """One frame's tracking.

    Attributes
    ----------
    points : (K, 3) float64 or None
        The layout's feature points in the face-fixed frame (``normalise_mesh``); None
        when no face was found.
    faces : int
        Faces found (the largest is tracked).
    mesh : (N, 3) float64 or None
        The tracked face's whole mesh in pixels, y up (``image_to_mesh``).
    seconds : float
        Time the model and the normalisation took.
    """

    points: np.ndarray | None
    faces: int
    mesh: np.ndarray | None
    seconds: float


#: Points of FaceMesh's own mesh; the attention mesh appends 10 iris points (5 an eye).
FACEMESH_POINTS = 468
#: FaceMesh's lid contours without the eye corners (MediaPipe's FACEMESH_RIGHT_EYE /
#: FACEMESH_LEFT_EYE; the points the page's eyelids.js replaces too), the subject's right
#: eye's upper then lower lid, then the left's: taken from the attention mesh.
LIDS = np.array(
    [
        *(246, 161, 160, 159, 158, 157, 173, 7, 163, 144, 145, 153, 154, 155),
        *(466, 388, 387, 386, 385, 384, 398, 249, 390, 373, 374, 380, 381, 382),
    ]
)
#: FaceMesh's nose tip, which pairs a face of the attention mesh with FaceMesh's.
_NOSE = 4


def _meshes(model: object, rgb: np.ndarray) -> list[np.ndarray]:
    """Every face ``model`` (a MediaPipe FaceMesh) finds in ``rgb``: normalised image
    coordinates, (N, 3) each."""
    found = model.process(rgb)  # type: ignore[attr-defined]
    return [
        np.array([(p.x, p.y, p.z) for p in face.landmark], dtype=np.float64)
        for face in found.multi_face_landmarks or []
    ]


class FaceTracker:
    """MediaPipe FaceMesh on RGB frames, the largest face normalised through ``layout``.

    Parameters
    ----------
    layout : Layout, optional
        Default the ``mediapipe_face_mesh`` table.
    max_faces : int
        Faces the model looks for; more than one lets it say there were two.
    static : bool
        Detect the face afresh in every frame (MediaPipe's ``static_image_mode``), the
        default. False lets MediaPipe crop each frame from the previous frame's landmarks
        instead (faster, but measured on the test video: landmarks drifted ~1 cm over five
        identical frames of an open jaw, while detecting each frame held them still).
    min_confidence : float
        Detection and tracking confidence in (0, 1].
    iris : bool
        The eyes refined, the default: MediaPipe's attention mesh (its
        ``refine_landmarks``) gives the lids (``LIDS``), and MediaPipe's iris model on a
        crop of each eye (``facecast.cli.eyelids``, as the /perform page runs it) the 10
        iris points of the 478-point mesh (the layout's last two features are the iris
        centres), the rest being FaceMesh's own 468. The attention mesh's own lips and
        brows superpose expressions worse (README, "The eyes clip", option (o)); its irises
        barely move when both eyes close, where the iris model's (and the page's, which
        the shipped generic set's irises are: README, option (z)) follow the lids down.
        Without LiteRT (no wheel for Intel macOS) the irises are the attention mesh's,
        with a ``RuntimeWarning``. False: FaceMesh's 468 points alone, which give the
        layout's first 24.
    """

    def __init__(
        self,
        layout: Layout | None = None,
        *,
        max_faces: int = 2,
        static: bool = True,
        min_confidence: float = 0.5,
        iris: bool = True,
    ) -> None:
        _, face_mesh = _modules()
        self.layout = layout or load_layout("mediapipe_face_mesh")
        if not (isinstance(max_faces, int) and 1 <= max_faces <= 8):
            raise InputError(f"max_faces must be 1-8, got {max_faces!r}")
        if not 0 < min_confidence <= 1:
            raise InputError(f"min_confidence must be in (0, 1], got {min_confidence!r}")

        def model(refine: bool) -> object:
            return face_mesh.FaceMesh(
                static_image_mode=static,
                max_num_faces=max_faces,
                refine_landmarks=refine,
                min_detection_confidence=min_confidence,
                min_tracking_confidence=min_confidence,
            )

        self._model = model(False)
        self._eyes = model(True) if iris else None
        self._irises: EyelidModel | None = None
        if iris:
            try:
                self._irises = EyelidModel()
            except ImportError as exc:
                # LiteRT has no wheel for every platform mediapipe has (Intel macOS).
                warnings.warn(
                    f"no iris model ({exc}): the irises are the attention mesh's, which barely "
                    "move on a blink, so a character on facecast's generic set reads blinks "
                    "weaker (README, option (z)); pip install ai-edge-litert where it has a wheel",
                    RuntimeWarning,
                    stacklevel=2,
                )

    def track(self, rgb: np.ndarray) -> Tracked:
        """Track one (H, W, 3) uint8 RGB frame."""
        if not (isinstance(rgb, np.ndarray) and rgb.ndim == 3 and rgb.shape[2] == 3):
            raise InputError(f"expected an (H, W, 3) RGB frame, got {np.shape(rgb)}")
        started = time.perf_counter()
        height, width = rgb.shape[:2]
        frame = np.ascontiguousarray(rgb, dtype=np.uint8)
        meshes = _meshes(self._model, frame)
        if not meshes:
            if self._irises is not None:
                self._irises.reset()
            return Tracked(None, 0, None, time.perf_counter() - started)
        # Two faces: follow the one nearest the camera, i.e. largest in the image.
        areas = [np.ptp(m[:, 0]) * width * np.ptp(m[:, 1]) * height for m in meshes]
        face = meshes[int(np.argmax(areas))]
        if self._eyes is not None:
            # The same face in the attention mesh: the one whose nose tip is nearest.
            refined = _meshes(self._eyes, frame)
            if not refined:  # no eyes to give: no face, rather than a frame of other points
                return Tracked(None, len(meshes), None, time.perf_counter() - started)
            eyes = min(refined, key=lambda m: float(np.linalg.norm(m[_NOSE, :2] - face[_NOSE, :2])))
            face = np.concatenate([face, eyes[FACEMESH_POINTS:]])
            face[LIDS] = eyes[LIDS]
            if self._irises is not None:  # the page's irises in place of the attention mesh's
                size = [width, height, width]
                face = self._irises.refine(frame, face * size, lids=False) / size
        mesh = image_to_mesh(face, width, height)
        try:
            points = normalise_mesh(mesh, self.layout)
        except InputError:  # a degenerate mesh is no face
            return Tracked(None, len(meshes), None, time.perf_counter() - started)
        return Tracked(points, len(meshes), mesh, time.perf_counter() - started)

    def close(self) -> None:
        for model in (self._model, self._eyes):
            if model is not None:
                model.close()  # type: ignore[attr-defined]

    def __enter__(self) -> FaceTracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class VideoSource:
    """Frames of a camera (an integer index) or a video file, as RGB arrays.

    Raises
    ------
    InputError
        ``no_camera`` when the camera or file cannot be opened.
    """

    def __init__(self, source: str | int) -> None:
        cv2, _ = _modules()
        self._cv2 = cv2
        self.is_camera = isinstance(source, int) or str(source).isdigit()
        self.source = int(source) if self.is_camera else str(source)
        self._capture = cv2.VideoCapture(self.source)
        if not self._capture.isOpened():
            what = f"camera {self.source}" if self.is_camera else f"video file {self.source}"
            raise InputError(
                f"cannot open {what} (absent, busy, or access denied)", code="no_camera"
            )
        fps = float(self._capture.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = fps if math.isfinite(fps) and fps > 0 else 30.0

    def frames(self, max_frames: int | None = None) -> Iterator[np.ndarray]:
        """RGB frames until the file ends (a camera: until ``max_frames``)."""
        count = 0
        while max_frames is None or count < max_frames:
            ok, bgr = self._capture.read()
            if not ok:
                return
            count += 1
            yield self._cv2.cvtColor(bgr, self._cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self._capture.release()

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
