"""Phonemes (IPA, any language espeak-ng speaks) -> visemes -> ARKit-52 mouth shapes (docs/voice.md, "Visemes").

Fifteen visemes (the usual lip-reading classes: bilabial closure, labiodental, dental, alveolar, velar, the
post-alveolar funnel, sibilant spread, rhotic rounding, the glides and the vowel classes by openness and
rounding), each an ARKit pose and a *dominance* per articulator group: how strongly the phoneme holds that group
against its neighbours when they are blended (targets.py). A bilabial holds the lips (closure) and the jaw almost
absolutely; an /h/ or a glottal stop holds nothing and takes its neighbours' shape; an /s/ holds the jaw but lets
its neighbours round the lips ("soup" against "see").

An IPA name is read symbol by symbol after dropping diacritics and length marks; a multi-vowel name (a diphthong)
gives one viseme per vowel with a share of the phoneme's duration, as does a consonant followed by a vowel.
Anything unknown is the neutral /h/ viseme, so a new espeak-ng symbol never fails, it only looks neutral.
"""

from __future__ import annotations

import unicodedata

import numpy as np

from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_COUNT

# Channel groups blended with their own dominance: the jaw (and what rides on it), the lips.
JAW_CHANNELS = ("jawOpen", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight",
                "tongueOut")
LIP_CHANNELS = ("mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft",
                "mouthStretchRight", "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthRollUpper",
                "mouthShrugLower", "mouthShrugUpper", "mouthDimpleLeft", "mouthDimpleRight")

# Viseme -> ARKit pose (a name without Left/Right sets both sides). mouthClose is not set here: the lips' closure
# is blended as its own channel (CLOSURE) and mouthClose = closure x jawOpen, so closed lips stay closed on any
# jaw opening (ARKit's mouthClose is "lips together despite jawOpen").
VISEMES: dict[str, dict[str, float]] = {
    "sil": {},
    "PP": {"jawOpen": 0.04, "mouthPress": 0.35, "mouthRollLower": 0.18, "mouthRollUpper": 0.12,
           "mouthShrugLower": 0.12},
    "FF": {"jawOpen": 0.08, "mouthRollLower": 0.45, "mouthUpperUp": 0.2, "mouthShrugUpper": 0.12,
           "mouthPress": 0.08},
    "TH": {"jawOpen": 0.14, "tongueOut": 0.35, "mouthLowerDown": 0.1, "mouthStretch": 0.08},
    "DD": {"jawOpen": 0.16, "mouthLowerDown": 0.1, "mouthStretch": 0.1},
    "kk": {"jawOpen": 0.22, "mouthLowerDown": 0.06, "mouthStretch": 0.06},
    "CH": {"jawOpen": 0.1, "mouthFunnel": 0.42, "mouthPucker": 0.22, "mouthUpperUp": 0.22, "mouthLowerDown": 0.22,
           "mouthShrugUpper": 0.12},
    "SS": {"jawOpen": 0.06, "mouthStretch": 0.3, "mouthSmile": 0.12, "mouthUpperUp": 0.12, "mouthLowerDown": 0.18},
    "RR": {"jawOpen": 0.14, "mouthFunnel": 0.3, "mouthPucker": 0.25},
    "W": {"jawOpen": 0.08, "mouthPucker": 0.8, "mouthFunnel": 0.3},
    "J": {"jawOpen": 0.12, "mouthSmile": 0.22, "mouthStretch": 0.28},
    "H": {"jawOpen": 0.2, "mouthLowerDown": 0.05},
    "aa": {"jawOpen": 0.6, "mouthLowerDown": 0.3, "mouthUpperUp": 0.08, "mouthStretch": 0.1},
    "E": {"jawOpen": 0.38, "mouthStretch": 0.25, "mouthSmile": 0.12, "mouthLowerDown": 0.2, "mouthUpperUp": 0.1},
    "I": {"jawOpen": 0.18, "mouthSmile": 0.3, "mouthStretch": 0.35, "mouthUpperUp": 0.1, "mouthLowerDown": 0.08,
          "mouthDimple": 0.1},
    "@": {"jawOpen": 0.28, "mouthLowerDown": 0.1},
    "O": {"jawOpen": 0.42, "mouthFunnel": 0.55, "mouthPucker": 0.2, "mouthLowerDown": 0.1},
    "U": {"jawOpen": 0.16, "mouthPucker": 0.7, "mouthFunnel": 0.35},
    "Y": {"jawOpen": 0.2, "mouthPucker": 0.55, "mouthFunnel": 0.2, "mouthStretch": 0.05},
}
# Viseme -> (jaw dominance, lip dominance, lip closure 0..1). The closure channel blends with the lip dominance.
DOMINANCE: dict[str, tuple[float, float, float]] = {
    "sil": (1.5, 1.5, 1.0),  # at rest the lips meet
    "PP": (6.0, 12.0, 1.0), "FF": (3.0, 6.0, 0.0), "TH": (2.0, 0.6, 0.0), "DD": (1.5, 0.3, 0.0),
    "kk": (1.0, 0.2, 0.0), "CH": (2.5, 5.0, 0.0), "SS": (3.0, 0.8, 0.0), "RR": (1.0, 2.0, 0.0),
    "W": (1.5, 4.0, 0.0), "J": (1.0, 1.0, 0.0), "H": (0.2, 0.2, 0.0),
    "aa": (1.0, 1.0, 0.0), "E": (1.0, 1.0, 0.0), "I": (1.0, 1.2, 0.0), "@": (0.8, 0.6, 0.0),
    "O": (1.0, 1.5, 0.0), "U": (1.0, 1.8, 0.0), "Y": (1.0, 1.6, 0.0),
}
VOWEL_VISEMES = ("aa", "E", "I", "@", "O", "U", "Y")

# IPA symbol -> viseme. Affricates are listed as two-symbol units and read first.
SYMBOLS: dict[str, str] = {
    **dict.fromkeys(("p", "b", "m", "ɓ", "ʙ"), "PP"),
    **dict.fromkeys(("f", "v", "ɱ", "ʋ", "β", "ɸ", "pf"), "FF"),
    **dict.fromkeys(("θ", "ð"), "TH"),
    **dict.fromkeys(("t", "d", "ɾ", "ɗ", "ʈ", "ɖ", "l", "ɫ", "ɭ", "ʎ", "ɬ", "r", "n", "ɲ", "ɳ"), "DD"),
    **dict.fromkeys(("k", "g", "ɡ", "q", "ɢ", "x", "ɣ", "χ", "ʁ", "ʀ", "ŋ", "ɴ", "c", "ɟ"), "kk"),
    **dict.fromkeys(("ʃ", "ʒ", "tʃ", "dʒ", "tɕ", "dʑ", "ʂ", "ʐ", "ʈʂ"), "CH"),
    **dict.fromkeys(("s", "z", "ɕ", "ʑ", "ç", "ʝ", "ts", "dz"), "SS"),
    **dict.fromkeys(("ɹ", "ɻ"), "RR"),
    **dict.fromkeys(("w", "ɥ", "ʍ"), "W"),
    "j": "J",
    **dict.fromkeys(("h", "ɦ", "ʔ", "ħ", "ʕ"), "H"),
    **dict.fromkeys(("a", "ɑ", "ɐ", "æ", "ä", "ʌ", "ɶ"), "aa"),
    **dict.fromkeys(("e", "ɛ"), "E"),
    **dict.fromkeys(("i", "ɪ", "ɨ", "ᵻ"), "I"),
    **dict.fromkeys(("ə", "ɚ", "ɘ", "ɜ", "ɝ", "ɯ", "ɤ"), "@"),
    **dict.fromkeys(("o", "ɔ", "ɒ"), "O"),
    **dict.fromkeys(("u", "ʊ"), "U"),
    **dict.fromkeys(("y", "ʏ", "ø", "œ", "ɵ"), "Y"),
}
_UNITS = sorted(SYMBOLS, key=len, reverse=True)
# Marks dropped before reading: length, stress, tie bars, and the modifier letters espeak-ng writes (aspiration,
# palatalisation, labialisation, ...); combining diacritics (nasal tilde, syllabic, non-syllabic) go with category Mn.
_DROPPED = set("ːˑˈˌ‿͜͡ʰʲʷˠˤⁿˡ'-|")
PAUSE = "_"


def _clean(ipa: str) -> str:
    return "".join(ch for ch in unicodedata.normalize("NFD", ipa)
                   if ch not in _DROPPED and unicodedata.category(ch) != "Mn")


def symbols_of(ipa: str) -> list[str]:
    """The known IPA symbols of a phoneme name, in order (affricates as one); unknown characters as themselves."""
    text, out, i = _clean(ipa), [], 0
    while i < len(text):
        unit = next((u for u in _UNITS if text.startswith(u, i)), text[i])
        out.append(unit)
        i += len(unit)
    return out


def visemes_of(ipa: str) -> list[tuple[str, float]]:
    """A phoneme's visemes with their shares of its duration (summing to 1): PAUSE is silence, one symbol one
    viseme, a diphthong or a consonant-vowel name one viseme per symbol (the first 55%, the rest evenly)."""
    if ipa == PAUSE or not ipa:
        return [("sil", 1.0)]
    visemes = [SYMBOLS.get(symbol, "H") for symbol in symbols_of(ipa)] or ["H"]
    merged = [v for k, v in enumerate(visemes) if k == 0 or v != visemes[k - 1]]  # "aa" from a long /aː/ etc.
    if len(merged) == 1:
        return [(merged[0], 1.0)]
    rest = 0.45 / (len(merged) - 1)
    return [(merged[0], 0.55)] + [(v, rest) for v in merged[1:]]


def pose(viseme: str) -> np.ndarray:
    """A viseme's ARKit pose [52] in ARKIT_BLENDSHAPES order (mouthClose 0: see CLOSURE)."""
    out = np.zeros(ARKIT_COUNT, np.float32)
    for name, weight in VISEMES[viseme].items():
        names = [name] if name in ARKIT_BLENDSHAPES else [name + "Left", name + "Right"]
        for side in names:
            out[ARKIT_BLENDSHAPES.index(side)] = weight
    return out


def pose_table() -> tuple[tuple[str, ...], np.ndarray]:
    """(viseme names, their poses [V, 52])."""
    names = tuple(VISEMES)
    return names, np.stack([pose(name) for name in names])


def channel_groups() -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks [52] of the jaw and the lip channels."""
    jaw = np.array([name in JAW_CHANNELS for name in ARKIT_BLENDSHAPES])
    lips = np.array([name in LIP_CHANNELS for name in ARKIT_BLENDSHAPES])
    return jaw, lips


def _check_tables() -> None:
    """The tables agree with each other and with ARKit's names (run at import: a typo fails loudly)."""
    assert set(VISEMES) == set(DOMINANCE), set(VISEMES) ^ set(DOMINANCE)
    assert set(SYMBOLS.values()) <= set(VISEMES)
    for viseme in VISEMES:
        for name in VISEMES[viseme]:
            sides = [name] if name in ARKIT_BLENDSHAPES else [name + "Left", name + "Right"]
            assert all(side in ARKIT_BLENDSHAPES for side in sides), (viseme, name)
            assert all(side in JAW_CHANNELS + LIP_CHANNELS for side in sides), (viseme, name)


_check_tables()

__all__ = ["DOMINANCE", "JAW_CHANNELS", "LIP_CHANNELS", "PAUSE", "SYMBOLS", "VISEMES", "VOWEL_VISEMES",
           "channel_groups", "pose", "pose_table", "symbols_of", "visemes_of"]
