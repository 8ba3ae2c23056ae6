"""Expression names as characters spell them, normalised to one vocabulary.

Maps ARKit camelCase, Perfect Sync capitals, ``_L``/``_R`` suffixes, VRM 0.x and 1.0
presets, VRoid's ``Fcl_`` clips and Oculus visemes onto ARKit's 52 names or VRM 1.0's preset names (the
table is docs/characters.md); it reads no file and knows nothing of meshes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = [
    "ARKIT_NAMES",
    "VRM_PRESETS",
    "NameMatch",
    "half_of",
    "normalise_name",
    "vrm0_preset",
]

#: The 52 ARKit blendshapes (ARFaceAnchor.BlendShapeLocation) as ARKit spells them, in Live
#: Link Face's order (Unreal's EARFaceBlendShape): the order of its UDP packet's values
#: (``sources.source_rig`` reads packets with it). CSV takes name their columns instead
#: (PascalCase).
ARKIT_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft",
    "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
    "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthUpperUpLeft", "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)  # fmt: skip

#: VRM 1.0's expression presets (VRMC_vrm.expressions.preset), "neutral" included.
VRM_PRESETS: tuple[str, ...] = (
    "happy", "angry", "sad", "relaxed", "surprised",
    "aa", "ih", "ou", "ee", "oh",
    "blink", "blinkLeft", "blinkRight",
    "lookUp", "lookDown", "lookLeft", "lookRight",
    "neutral",
)  # fmt: skip

# VRM 0.x blendShapeGroups[*].presetName -> the VRM 1.0 preset (VRM 1.0 migration guide).
_VRM0_PRESETS = {
    "neutral": "neutral", "a": "aa", "i": "ih", "u": "ou", "e": "ee", "o": "oh",
    "blink": "blink", "blink_l": "blinkLeft", "blink_r": "blinkRight",
    "joy": "happy", "angry": "angry", "sorrow": "sad", "fun": "relaxed",
    "surprised": "surprised",
    "lookup": "lookUp", "lookdown": "lookDown", "lookleft": "lookLeft", "lookright": "lookRight",
}  # fmt: skip

# VRoid Studio's face clips (morph targets of its Face mesh) that match a VRM preset. Its
# other Fcl_ clips move one part (Fcl_BRW_*, Fcl_EYE_Joy, Fcl_MTH_Large, Fcl_HA_*) or hide
# one (Fcl_EYE_Iris_Hide): no ARKit shape or preset matches them, so they stay unpaired.
_FCL_CLIPS = {
    "fcl_all_neutral": "neutral",
    "fcl_all_joy": "happy", "fcl_all_angry": "angry", "fcl_all_sorrow": "sad",
    "fcl_all_fun": "relaxed", "fcl_all_surprised": "surprised",
    "fcl_mth_a": "aa", "fcl_mth_i": "ih", "fcl_mth_u": "ou", "fcl_mth_e": "ee",
    "fcl_mth_o": "oh",
    "fcl_eye_close": "blink", "fcl_eye_close_l": "blinkLeft", "fcl_eye_close_r": "blinkRight",
}  # fmt: skip

# Oculus (Meta) visemes, as Ready Player Me and other lip-sync rigs name their morph
# targets: the five vowels are VRM's (aa あ, E え, I い, O お, U う); silence is the rest
# pose. The consonants (viseme_PP, _FF, _TH, _DD, _kk, _CH, _SS, _nn, _RR) have no preset
# and keep their own names.
_VISEMES = {
    "viseme_sil": "neutral",
    "viseme_aa": "aa", "viseme_e": "ee", "viseme_i": "ih", "viseme_o": "oh", "viseme_u": "ou",
}  # fmt: skip

# Side suffixes, tried on the key (lower case, separators kept): _L, .L, -L, Left, _Left...
_SIDE = re.compile(r"(?:[_.\- ]?(left|right)|[_.\-](l|r))$")


def _key(name: str) -> str:
    """Lower case, side spelt out, separators and spaces dropped: the comparison key."""
    lowered = name.strip().lower()
    match = _SIDE.search(lowered)
    if match is not None:
        side = "left" if (match.group(1) or match.group(2)).startswith("l") else "right"
        lowered = lowered[: match.start()] + side
    return re.sub(r"[_.\- ]", "", lowered)


_ARKIT_KEYS = {_key(n): n for n in ARKIT_NAMES}
_VRM_KEYS = {_key(n): n for n in VRM_PRESETS}
# Perfect Sync and some exporters split the two ARKit shapes that have no side.
_HALVES = {"browinnerupleft", "browinnerupright", "cheekpuffleft", "cheekpuffright"}


@dataclass(frozen=True)
class NameMatch:
    """What a name became: ``name`` (an ARKit name, a VRM preset, or None) and ``how``."""

    name: str | None
    how: str


def vrm0_preset(preset: str) -> str | None:
    """The VRM 1.0 preset of a VRM 0.x ``presetName`` (None for "unknown" or others)."""
    return _VRM0_PRESETS.get(preset.strip().lower())


def normalise_name(name: str) -> NameMatch:
    """The ARKit name or VRM preset ``name`` stands for, and which rule matched.

    Rules, in order: a VRoid ``Fcl_`` clip with a preset twin; an Oculus vowel viseme
    (``viseme_aa``, ``viseme_E``, ``viseme_I``, ``viseme_O``, ``viseme_U``); an ARKit name compared
    without case, separators and with ``_L``/``_R``/``Left``/``Right`` suffixes unified
    (``JawOpen``, ``eyeBlink_L``, ``EyeBlinkLeft``); a VRM 1.0 preset or a VRM 0.x preset
    name (``A``, ``Joy``, ``Blink_L``); the same after dropping an exporter's prefix up to
    the last ``.`` (``blendShape1.jawOpen``). ``name`` None means no rule matched; ``how``
    then says what was tried.
    """
    stripped = name.strip()
    if not stripped:
        return NameMatch(None, "empty name")
    fcl = _FCL_CLIPS.get(stripped.lower())
    if fcl is not None:
        return NameMatch(fcl, "VRoid Fcl_ clip")
    viseme = _VISEMES.get(stripped.lower())
    if viseme is not None:
        return NameMatch(viseme, "Oculus viseme")
    if stripped.lower().startswith("fcl_"):
        return NameMatch(
            None,
            "VRoid Fcl_ clip without an ARKit or VRM preset twin (it moves or hides one part)",
        )
    for candidate, prefix in ((stripped, ""), (stripped.rsplit(".", 1)[-1], "prefix dropped, ")):
        if prefix and (candidate == stripped or candidate.lower() in ("l", "r")):
            break
        match = _match(candidate)
        if match.name is not None:
            return NameMatch(match.name, prefix + match.how)
    key = _key(stripped)
    if key in _HALVES:
        return NameMatch(
            None, "one side of an ARKit shape that has none (joined when both sides exist)"
        )
    return NameMatch(
        None,
        "not an ARKit, Perfect Sync, VRM 0.x/1.0 preset or VRoid Fcl_ name (compared without "
        "case and separators, _L/_R as Left/Right)",
    )


def _match(name: str) -> NameMatch:
    if name in ARKIT_NAMES:
        return NameMatch(name, "ARKit name")
    if name in VRM_PRESETS:
        return NameMatch(name, "VRM 1.0 preset")
    key = _key(name)
    if key in _ARKIT_KEYS:
        arkit = _ARKIT_KEYS[key]
        rules = []
        if name[:1].isupper():
            rules.append("Perfect Sync capitals")
        if re.search(r"[_.\-](l|r)$", name.lower()):
            rules.append("_L/_R suffix")
        return NameMatch(
            arkit, "ARKit name, " + (" and ".join(rules) or "case or separators differ")
        )
    preset = _VRM0_PRESETS.get(name.strip().lower())
    if preset is not None:
        return NameMatch(preset, "VRM 0.x preset")
    if key in _VRM_KEYS:
        return NameMatch(_VRM_KEYS[key], "VRM 1.0 preset, case or separators differ")
    return NameMatch(None, "")


def half_of(name: str) -> tuple[str, str] | None:
    """``(ARKit shape, "left" | "right")`` when ``name`` is one side of browInnerUp or cheekPuff
    (``browInnerUp_L``, ``CheekPuffRight``), which ARKit moves as one shape; else None."""
    key = _key(name.strip().rsplit(".", 1)[-1] if "." in name.strip()[:-2] else name)
    for arkit in ("browInnerUp", "cheekPuff"):
        for side in ("left", "right"):
            if key == _key(arkit) + side:
                return arkit, side
    return None
