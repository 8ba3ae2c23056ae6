"""Full strength where it shows (issue 32): the generic source's exact poses, published to a
channel of a real uvicorn, reach each kind of uploaded avatar's watcher at full strength.

Every avatar is the suite's own, named as that kind of avatar names its morph targets and
VRM expressions (``tests.rig._named_avatars``: no ICT-FaceKit needed, since a rig's weights
depend on which names pair, and the ICT-FaceKit avatars of ``tests.rig._avatars`` give the
same figures), uploaded through ``PUT /v1/characters/{id}`` and fitted there with the
defaults a user gets; one publisher sends the poses, one watcher per avatar receives its
weights. docs/characters.md's "Full strength" table holds the figures.
"""

from __future__ import annotations

import anyio
import httpx
import numpy as np
import pytest

from facecast.rig.characters.generic import generic_sources
from facecast.server.settings import Settings
from facecast.server.testing import run_server
from tests.channels._helpers import Publisher, Watcher
from tests.rig._named_avatars import avatar

_ARKIT = {
    "blink": ("eyeBlinkLeft", "eyeBlinkRight"),
    "mouth open": ("jawOpen",),
    "smile": ("mouthSmileLeft", "mouthSmileRight"),
}
_PRESETS = {"blink": ("blinkLeft", "blinkRight"), "mouth open": ("aa",), "smile": ("happy",)}
#: Per avatar kind (a ``_avatars`` variant): the morphs each pose must drive.
KINDS = {
    "arkit": _ARKIT,
    "perfect_sync": _ARKIT,
    "vrm0": _ARKIT,  # ARKit shapes and VRM 0.x presets binding them
    "vrm1": _ARKIT,
    "visemes": _ARKIT,  # ARKit shapes and Oculus visemes, as Ready Player Me writes them
    "fcl": _PRESETS,  # VRoid's Fcl_ clips through VRM 0.x presets, nothing else
    "vrm0_presets": _PRESETS,  # VRM 0.x presets only, look presets included
    # VRoid clips and Perfect Sync shapes, its JawOpen all zeros: VRoid's A opens the mouth.
    "vroid_sync": {**_ARKIT, "mouth open": ("aa",)},
}
#: The thresholds of issue 32: a closed eye's blink, the mouth-open morph, the smile;
#: every expression at the exact neutral.
AT_LEAST = {"blink": 0.9, "mouth open": 0.9, "smile": 0.8}
NEUTRAL_AT_MOST = 0.03
#: Presets that would drive a whole face: never paired beside the ARKit shapes they mix.
WHOLE_FACE = ("happy", "relaxed", "angry", "sad", "surprised", "blink")


def exact_poses() -> dict[str, np.ndarray]:
    """The generic source's neutral, both eyes closed, the jaw open and a smile (K, 3)."""
    generic = generic_sources()
    neutral = generic.points[0]

    def pose(*shapes: str) -> np.ndarray:
        return neutral + sum(generic.points[generic.names.index(s)] - neutral for s in shapes)

    return {
        "neutral": neutral,
        "blink": pose("eyeBlinkLeft", "eyeBlinkRight"),
        "mouth open": pose("jawOpen"),
        "smile": pose("mouthSmileLeft", "mouthSmileRight"),
    }


@pytest.fixture(scope="module")
def received(tmp_path_factory) -> dict[str, dict]:
    """Per avatar kind: its upload's answer and, per pose, the weights its watcher got."""

    settings = Settings(rigs_dir=tmp_path_factory.mktemp("rigs"))

    async def run() -> dict[str, dict]:
        out: dict[str, dict] = {}
        async with run_server(settings) as server:
            async with httpx.AsyncClient(base_url=server.base_url, timeout=300) as http:
                for kind in KINDS:
                    put = await http.put(f"/v1/characters/{kind}", content=avatar(kind))
                    assert put.status_code == 201, (kind, put.text)
                    out[kind] = {"upload": put.json(), "weights": {}}
            watchers = {kind: await Watcher.open(server.ws_url, "stage", kind) for kind in KINDS}
            publisher = await Publisher.open(server.ws_url, "stage", "arkit")
            try:
                for seq, (pose, points) in enumerate(exact_poses().items(), start=1):
                    await publisher.send(seq, points.astype(np.float32))
                    for kind, watcher in watchers.items():
                        result = await watcher.result_with_seq(seq, timeout=30)
                        assert result.seq == seq
                        out[kind]["weights"][pose] = np.asarray(result.weights, dtype=np.float64)
            finally:
                await publisher.close()
                for watcher in watchers.values():
                    await watcher.close()
        return out

    return anyio.run(run)


def weights_of(got: dict, pose: str) -> dict[str, float]:
    names = got["upload"]["names"]
    return dict(zip(names, got["weights"][pose].tolist(), strict=True))


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("pose", list(AT_LEAST))
def test_an_exact_pose_drives_its_morphs_at_full_strength(received, kind, pose):
    weights = weights_of(received[kind], pose)

    for morph in KINDS[kind][pose]:
        assert weights[morph] >= AT_LEAST[pose], (kind, pose, morph, weights)


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_exact_neutral_drives_no_expression(received, kind):
    weights = weights_of(received[kind], "neutral")

    moved = {n: w for n, w in weights.items() if n != "neutral" and w > NEUTRAL_AT_MOST}
    assert not moved, (kind, moved)


@pytest.mark.parametrize("kind", [k for k, v in KINDS.items() if v["smile"] != ("happy",)])
def test_a_smile_stays_on_the_mouth_where_the_avatar_has_mouth_only_shapes(received, kind):
    got = received[kind]
    weights = weights_of(got, "smile")

    assert not set(WHOLE_FACE) & set(got["upload"]["names"]), got["upload"]["names"]
    assert max(weights[n] for n in ("eyeBlinkLeft", "eyeBlinkRight")) <= NEUTRAL_AT_MOST
    assert weights["jawOpen" if "jawOpen" in weights else "aa"] <= NEUTRAL_AT_MOST


def test_the_upload_reports_what_moves_nothing_and_maps_visemes(received):
    entries = {
        kind: {e["authored"]: e for e in received[kind]["upload"]["pairing"]["entries"]}
        for kind in ("vroid_sync", "visemes")
    }

    still = entries["vroid_sync"]["JawOpen"]
    assert not still["paired"] and "moves no vertex" in still["reason"], still
    assert "jawOpen" not in received["vroid_sync"]["upload"]["names"]
    vowels = {"viseme_aa": "aa", "viseme_E": "ee", "viseme_I": "ih", "viseme_O": "oh"}
    for viseme, preset in {**vowels, "viseme_U": "ou"}.items():
        entry = entries["visemes"][viseme]
        assert entry["expression"] == preset and "Oculus viseme" in entry["reason"], entry
        # The avatar's ARKit shapes drive its mouth: the viseme would drive it twice.
        assert not entry["paired"] and "own ARKit shapes" in entry["reason"], entry
