"""Expression names as each kind of VMC receiver spells them: VRM 0.x, VRM 1.0, Perfect Sync.

Pure tables and one lookup; it must not send anything (``vmc`` does). VMC blend shape
names are case-sensitive (VMC protocol spec, "VRM BlendShapeProxyValue"), so a name
that is right except for its case does nothing on most receivers.

A rig expression name is matched case-insensitively against three vocabularies:

- **VRM expressions** (`VRM_EXPRESSIONS`): the VRM 1.0 presets and the demo's names
  (``aa``, ``happy``, ``blinkLeft``...). VRM 0.x spells the presets differently (``A``,
  ``Joy``, ``Blink_L``; the table in the VMC spec); VRM 0.x has no "surprised" preset,
  so ``vrm0`` sends ``Surprised``, the custom clip VRoid Studio's VRM 0.x models carry.
- **ARKit names** (``ARKIT_NAMES``, 52): ``perfectsync`` sends them in PascalCase
  (``jawOpen`` -> ``JawOpen``), the clip names of hinzka's Perfect Sync convention that
  VSeeFace and other VMC apps look for. ``vrm0`` does too, except the two blinks, which
  it sends as the presets every VRM 0.x avatar has (``Blink_L``, ``Blink_R``); ``vrm1``
  sends the blinks as ``blinkLeft``/``blinkRight`` and the other ARKit names unchanged.
- Anything else (a rig's custom clip) is sent unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from facecast.rig.sources.source_rig import ARKIT_NAMES

__all__ = [
    "DEFAULT_CONVENTION",
    "NAME_CONVENTIONS",
    "VRM_EXPRESSIONS",
    "vmc_names",
]

#: Receiver conventions `vmc_names` knows; the default is what VSeeFace (a VRM 0.x app,
#: with Perfect Sync support) expects.
NAME_CONVENTIONS = ("vrm0", "vrm1", "perfectsync")
DEFAULT_CONVENTION = "vrm0"

#: VRM 1.0 expression name -> its VRM 0.x blend shape clip (the VMC spec's table, plus
#: the presets VRM 1.0 kept; ``surprised`` is VRoid's custom clip, not a 0.x preset).
_VRM1_TO_VRM0: dict[str, str] = {
    "aa": "A", "ih": "I", "ou": "U", "ee": "E", "oh": "O",
    "happy": "Joy", "angry": "Angry", "sad": "Sorrow", "relaxed": "Fun",
    "surprised": "Surprised",
    "blink": "Blink", "blinkLeft": "Blink_L", "blinkRight": "Blink_R",
    "lookUp": "LookUp", "lookDown": "LookDown", "lookLeft": "LookLeft", "lookRight": "LookRight",
    "neutral": "Neutral",
}  # fmt: skip

#: Lower-case name a rig may use -> the VRM 1.0 expression it means: the 1.0 names, the
#: 0.x names, and the demo's / common aliases.
VRM_EXPRESSIONS: dict[str, str] = {
    **{name.lower(): name for name in _VRM1_TO_VRM0},
    **{clip.lower(): name for name, clip in _VRM1_TO_VRM0.items()},
    "a": "aa", "i": "ih", "u": "ou", "oo": "ou", "e": "ee", "o": "oh",
    "joy": "happy", "anger": "angry", "sorrow": "sad", "fun": "relaxed",
    "surprise": "surprised",
}  # fmt: skip

_ARKIT_BY_LOWER = {name.lower(): name for name in ARKIT_NAMES}
#: ARKit blinks -> the VRM 1.0 expression a VRM avatar without Perfect Sync has for them.
_ARKIT_BLINKS = {"eyeBlinkLeft": "blinkLeft", "eyeBlinkRight": "blinkRight"}


def _vmc_name(name: str, convention: str) -> str:
    key = name.lower()
    arkit = _ARKIT_BY_LOWER.get(key)
    if arkit is not None:
        if convention == "perfectsync":
            return arkit[0].upper() + arkit[1:]
        blink = _ARKIT_BLINKS.get(arkit)
        if convention == "vrm1":
            return blink or arkit
        return _VRM1_TO_VRM0[blink] if blink else arkit[0].upper() + arkit[1:]
    expression = VRM_EXPRESSIONS.get(key)
    if expression is None:
        return name
    return expression if convention == "vrm1" else _VRM1_TO_VRM0[expression]


def vmc_names(
    names: Sequence[str],
    convention: str = DEFAULT_CONVENTION,
    overrides: Mapping[str, str] | None = None,
) -> tuple[str, ...]:
    """The VMC blend shape name for each rig expression name, for one receiver convention.

    Parameters
    ----------
    names : sequence of str
        Rig expression names (without the neutral).
    convention : {"vrm0", "vrm1", "perfectsync"}
        How the receiver spells names (module docstring).
    overrides : mapping, optional
        Exact rig name -> VMC name; wins over the convention.

    Raises
    ------
    ValueError
        An unknown convention.
    """
    if convention not in NAME_CONVENTIONS:
        raise ValueError(
            f"unknown VMC name convention {convention!r}; expected one of "
            f"{', '.join(NAME_CONVENTIONS)}"
        )
    overrides = dict(overrides or {})
    return tuple(overrides.get(n) or _vmc_name(n, convention) for n in names)
