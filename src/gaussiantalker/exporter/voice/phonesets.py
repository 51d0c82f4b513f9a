"""festival's non-English phone sets -> IPA, so Italian, Czech, Finnish and Catalan voices give the same viseme
targets as every other engine (docs/voice.md, "Voices").

Each voice names its phones in its language's festival phone set (listed by `PhoneSet.description`); the tables
below map every name of the four sets to IPA (only as finely as the visemes read it: a Czech ř is the trill r̝, an
alveolar like r). A vowel may carry a stress digit ("a1": Italian, Catalan) and a phone a length mark ("a:",
"k:": Finnish, Czech); both are read off the name here. Czech and Finnish stress every word's first syllable and
their voices mark no stress, so a word's first vowel is taken as stressed (segments.phonemes_of). Pauses of every
set map to the visemes' pause name. A phone outside its table is a ValueError that names it, so a new voice's
unmapped phone fails loudly instead of looking neutral.
"""

from __future__ import annotations

from dataclasses import dataclass

from .visemes import PAUSE, SYMBOLS, VOWEL_VISEMES, symbols_of


@dataclass(frozen=True)
class PhoneSet:
    """One festival phone set: each phone's IPA (without stress and length), the names that are pauses, and whether
    its language stresses every word's first syllable (Czech, Finnish: festival's voices mark no stress there)."""

    name: str
    ipa: dict[str, str]
    silences: frozenset[str]
    initial_stress: bool = False

    def _base(self, phone: str) -> tuple[str, bool]:
        """(the table's name, long?) of a phone: its stress digit and length mark dropped."""
        name = phone.strip()
        long = name.endswith(":") and name[:-1] in self.ipa
        if long:
            name = name[:-1]
        if name not in self.ipa and name[-1:] == "1" and name[:-1] in self.ipa:
            name = name[:-1]
        return name, long

    def is_silence(self, phone: str) -> bool:
        """Whether a phone name is one of this set's pauses."""
        return phone.strip() in self.silences

    def is_vowel(self, phone: str) -> bool:
        """Whether a phone is a vowel (its IPA's first symbol a vowel viseme's)."""
        if self.is_silence(phone):
            return False
        name, _ = self._base(phone)
        symbols = symbols_of(self.ipa[name]) if name in self.ipa else []
        return bool(symbols) and SYMBOLS.get(symbols[0]) in VOWEL_VISEMES

    def stressed(self, phone: str) -> bool:
        """Whether a phone's name marks it stressed (a vowel's digit 1: Italian, Catalan)."""
        name = phone.strip()
        return name[-1:] == "1" and name[:-1] in self.ipa and self.is_vowel(name)

    def ipa_of(self, phone: str) -> str:
        """IPA of a phone (a long one with the length mark), PAUSE for a pause; ValueError naming an unknown one."""
        if self.is_silence(phone):
            return PAUSE
        name, long = self._base(phone)
        if name not in self.ipa:
            raise ValueError(f"not a phone of festival's {self.name} set: {phone!r}")
        return self.ipa[name] + ("ː" if long else "")


ITALIAN = PhoneSet("italian", {
    "i": "i", "e": "e", "E": "ɛ", "a": "a", "o": "o", "O": "ɔ", "u": "u", "j": "j", "w": "w",
    "p": "p", "t": "t", "k": "k", "b": "b", "d": "d", "g": "ɡ", "f": "f", "s": "s", "S": "ʃ", "v": "v", "z": "z",
    "Z": "ʒ", "ts": "ts", "tS": "tʃ", "dz": "dz", "dZ": "dʒ", "m": "m", "n": "n", "J": "ɲ", "ng": "ŋ", "nf": "ɱ",
    "l": "l", "L": "ʎ", "r": "r",
}, frozenset({"#"}))

CZECH = PhoneSet("czech", {
    "a": "a", "e": "e", "i": "ɪ", "o": "o", "u": "u",
    "b": "b", "c": "ts", "c~": "tʃ", "ch": "x", "d": "d", "d~": "ɟ", "dz": "dz", "dz~": "dʒ", "f": "f", "g": "ɡ",
    "h": "ɦ", "j": "j", "k": "k", "l": "l", "m": "m", "n": "n", "n*": "ŋ", "n~": "ɲ", "p": "p", "r": "r",
    "r~": "r̝", "r~*": "r̝̊", "s": "s", "s~": "ʃ", "t": "t", "t~": "c", "v": "v", "z": "z", "z~": "ʒ",
}, frozenset({"#", "_"}), initial_stress=True)

# Suopuhe's Finnish set: @ is ä, 7 is ö, & the Swedish å; T and D the dental fricatives of loanwords.
FINNISH = PhoneSet("finnish", {
    "a": "ɑ", "e": "e", "i": "i", "o": "o", "u": "u", "y": "y", "@": "æ", "7": "ø", "&": "ɔ",
    "p": "p", "t": "t", "k": "k", "b": "b", "d": "d", "g": "ɡ", "f": "f", "T": "θ", "D": "ð", "s": "s", "z": "z",
    "S": "ʃ", "Z": "ʒ", "h": "h", "v": "ʋ", "m": "m", "n": "n", "N": "ŋ", "l": "l", "L": "ʎ", "r": "r", "j": "j",
    "w": "w",
}, frozenset({"#", "##"}), initial_stress=True)

CATALAN = PhoneSet("catalan", {
    "ax": "ə", "a": "a", "e": "e", "E": "ɛ", "i": "i", "o": "o", "O": "ɔ", "u": "u",
    "b": "b", "d": "d", "f": "f", "g": "ɡ", "j": "j", "J": "ɲ", "k": "k", "l": "l", "L": "ʎ", "m": "m", "n": "n",
    "p": "p", "r": "ɾ", "rr": "r", "s": "s", "S": "ʃ", "t": "t", "w": "w", "z": "z", "Z": "ʒ",
}, frozenset({"pau", "_", "#"}))

BY_LANGUAGE: dict[str, PhoneSet] = {"it": ITALIAN, "cs": CZECH, "fi": FINNISH, "ca": CATALAN}

__all__ = ["BY_LANGUAGE", "CATALAN", "CZECH", "FINNISH", "ITALIAN", "PhoneSet"]
