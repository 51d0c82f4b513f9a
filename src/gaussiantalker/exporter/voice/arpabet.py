"""ARPAbet phone names -> IPA, so the phones of festival, flite and pocketsphinx become the same viseme targets as
espeak-ng's IPA phonemes (docs/voice.md, "Voices").

ARPAbet is the American-English phone set of CMUdict: pocketsphinx's en-US model writes it in capitals, festival's
and flite's US voices in lower case (festival's "radio" set adds a few allophones: flap, syllabic consonants). A
vowel may carry a stress digit (0 none, 1 primary, 2 secondary); `split_stress` reads it. Pauses and silences of
every engine map to the visemes' pause name.
"""

from __future__ import annotations

from .visemes import PAUSE

# Unstressed AH is a schwa in CMUdict's own convention; a stressed one is the open-mid /ʌ/ (see `ipa_of`).
IPA: dict[str, str] = {
    "aa": "ɑ", "ae": "æ", "ah": "ʌ", "ao": "ɔ", "aw": "aʊ", "ax": "ə", "axr": "ɚ", "ay": "aɪ", "eh": "ɛ",
    "er": "ɝ", "ey": "eɪ", "ih": "ɪ", "ix": "ɨ", "iy": "i", "ow": "oʊ", "oy": "ɔɪ", "uh": "ʊ", "uw": "u",
    "ux": "u",  # a fronted /u/: rounded all the same
    "b": "b", "ch": "tʃ", "d": "d", "dh": "ð", "dx": "ɾ", "el": "l", "em": "m", "en": "n", "f": "f", "g": "ɡ",
    "hh": "h", "hv": "ɦ", "jh": "dʒ", "k": "k", "l": "l", "m": "m", "n": "n", "ng": "ŋ", "nx": "ɾ̃", "p": "p",
    "q": "ʔ", "r": "ɹ", "s": "s", "sh": "ʃ", "t": "t", "th": "θ", "v": "v", "w": "w", "wh": "ʍ", "y": "j",
    "z": "z", "zh": "ʒ",
}
SILENCES = frozenset({"pau", "sil", "h#", "sp", "spn", "brth", "<s>", "</s>", "+nsn+", "+spn+", "+breath+",
                      "+cough+", "+noise+", "+smack+", "+um+", "+uh+"})
VOWELS = frozenset({"aa", "ae", "ah", "ao", "aw", "ax", "axr", "ay", "eh", "er", "ey", "ih", "ix", "iy", "ow",
                    "oy", "uh", "uw", "ux"})


def split_stress(phone: str) -> tuple[str, int | None]:
    """("aa", 1) of "AA1": the lower-case name and its stress digit (None when the phone carries none)."""
    name = phone.strip().lower()
    if name[-1:] in ("0", "1", "2") and name[:-1] in VOWELS:
        return name[:-1], int(name[-1])
    return name, None


def is_silence(phone: str) -> bool:
    """Whether an engine's phone name is a pause, a silence or a filler (breath, noise)."""
    return split_stress(phone)[0] in SILENCES


def ipa_of(phone: str) -> str:
    """IPA of an ARPAbet phone in any case, stress digit allowed (PAUSE for silences and fillers); ValueError
    naming the phone when it is none of them."""
    name, stress = split_stress(phone)
    if name in SILENCES:
        return PAUSE
    if name == "ah" and stress == 0:
        return "ə"
    if name not in IPA:
        raise ValueError(f"not an ARPAbet phone: {phone!r}")
    return IPA[name]


__all__ = ["IPA", "SILENCES", "VOWELS", "ipa_of", "is_silence", "split_stress"]
