"""What the voice drivers train and are measured on: random sentences in several languages, spoken by espeak-ng
voices, English ones spoken by festival's and flite's more natural voices, and Italian, Czech, Finnish and Catalan
ones by festival's voices of those languages, at random rates and pitches (docs/voice.md, "Training data" and
"Voices").

Sentences are drawn from small word lists (common words rich in the phonemes lips show, written here so nothing is
downloaded) mixed with pseudo-words (the language's spelling of random syllables, for phoneme combinations the
lists lack), with commas, full stops, questions and exclamations for phrase rhythm. Training and held-out sets
come from disjoint seed streams and disjoint voices; `heldout_specs` also checks that none of its sentences is a
training sentence. One family of voices is never trained on (HELDOUT_FAMILY: festival's diphone voices), so the
measurements include voices made another way than any the drivers heard.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .festival import WORLD_VOICES

WORDS = {
    "en": ("people", "maybe", "about", "problem", "simple", "bring", "number", "morning", "power", "member",
           "move", "be", "my", "me", "put", "back", "big", "more", "much", "both", "open", "paper", "happy",
           "before", "remember", "tomorrow", "everybody", "thank", "you", "very", "would", "what", "where", "who",
           "should", "sure", "shoe", "choose", "judge", "thing", "this", "that", "those", "with", "view", "fine",
           "five", "water", "world", "word", "sleep", "see", "say", "zero", "keep", "car", "go", "good", "look",
           "book", "rule", "room", "food", "two", "new", "now", "how", "out", "boy", "joy", "light", "night",
           "help", "hope", "home", "phone", "music", "voice", "question", "answer", "little", "bottle", "apple"),
    "de": ("bitte", "danke", "Morgen", "Abend", "immer", "mehr", "Mann", "Mutter", "Vater", "Bruder", "Baum",
           "Blume", "bleiben", "Brot", "Milch", "Wasser", "Schule", "schön", "Frühling", "für", "über", "Tür",
           "müde", "Hund", "Katze", "Zeit", "zwei", "drei", "vier", "fünf", "Pferd", "Apfel", "Kopf", "Haus",
           "Mädchen", "ich", "du", "wir", "sprechen", "machen", "Buch", "Woche", "Vogel", "Öl", "böse", "Frau",
           "heute", "morgen", "gestern", "Stadt", "Straße", "Platz", "mit", "ohne", "warum", "wo", "wie"),
    "fr": ("bonjour", "merci", "beaucoup", "peut-être", "maman", "papa", "pomme", "pain", "beau", "belle",
           "bien", "même", "moi", "toi", "vous", "nous", "tout", "rouge", "bleu", "feu", "fleur", "heure", "sœur",
           "lune", "plume", "jupe", "chose", "chemin", "jamais", "toujours", "pourquoi", "comment", "voiture",
           "maison", "monde", "ombre", "pluie", "soleil", "oui", "non", "midi", "minuit", "parler", "manger",
           "boire", "partir", "vouloir", "pouvoir", "petit", "grand", "bonne", "nuit", "deux", "cinq"),
    "es": ("hola", "gracias", "por", "favor", "buenos", "días", "mamá", "papá", "mucho", "poco", "bueno",
           "malo", "bonito", "playa", "pueblo", "mundo", "muy", "mesa", "boca", "mano", "perro", "gato", "agua",
           "fuego", "tiempo", "siempre", "nunca", "mañana", "noche", "chico", "chica", "queso", "zapato", "cielo",
           "camino", "pájaro", "mariposa", "puerta", "ventana", "hablar", "comer", "beber", "vivir", "amigo"),
    "it": ("ciao", "grazie", "prego", "bambino", "bello", "bella", "buono", "mamma", "papà", "pane", "pasta",
           "pomodoro", "mela", "molto", "poco", "sempre", "mai", "oggi", "domani", "sole", "luna", "mare",
           "montagna", "piazza", "città", "chiesa", "gnocchi", "figlio", "famiglia", "perché", "come", "dove",
           "parlare", "mangiare", "bere", "dormire", "vivere", "amore", "tempo", "mondo", "uomo", "donna"),
    "pt": ("olá", "obrigado", "bom", "dia", "boa", "noite", "mãe", "pai", "muito", "pouco", "bonito", "pão",
           "peixe", "praia", "mundo", "sempre", "nunca", "amanhã", "hoje", "chuva", "sol", "mar", "casa",
           "cidade", "porta", "janela", "falar", "comer", "beber", "viver", "amigo", "amor", "tempo", "coração",
           "palavra", "menino", "menina", "bem", "mal", "por", "favor", "quem", "onde", "porque"),
    "nl": ("hallo", "dank", "je", "wel", "goedemorgen", "mooi", "moeder", "vader", "broer", "boom", "bloem",
           "brood", "melk", "water", "school", "huis", "muis", "fiets", "prachtig", "misschien", "morgen",
           "vandaag", "gisteren", "waarom", "waar", "hoe", "praten", "eten", "drinken", "lopen", "kopen",
           "boek", "week", "maan", "zon", "zee", "meisje", "jongen", "mensen", "geluk", "liefde", "tijd"),
    "pl": ("dzień", "dobry", "proszę", "dziękuję", "mama", "tata", "bardzo", "pięknie", "miasto", "morze",
           "ptak", "babcia", "dziadek", "mleko", "woda", "chleb", "książka", "szkoła", "przyjaciel", "pies",
           "kot", "dom", "okno", "drzwi", "może", "zawsze", "nigdy", "jutro", "dzisiaj", "mówić", "pić", "jeść",
           "być", "mieć", "czas", "miłość", "słońce", "księżyc", "góra", "rzeka"),
    # festival's other languages (WORLD_FAMILY): spelt in what their voices read (Latin-1, Czech in Latin-2)
    "cs": ("dobrý", "den", "prosím", "děkuji", "maminka", "tatínek", "babička", "pivo", "ryba", "mléko", "voda",
           "chleba", "kniha", "škola", "přítel", "pes", "kočka", "dům", "okno", "možná", "vždycky", "nikdy",
           "zítra", "dnes", "mluvit", "pít", "jíst", "být", "mít", "čas", "láska", "slunce", "měsíc", "hora",
           "řeka", "most", "jablko", "modrý", "bílý", "malý", "velký", "pomalu", "bratr", "večer", "ráno", "mapa",
           "poprvé", "obchod", "hudba", "vlak"),
    "fi": ("hyvää", "päivää", "kiitos", "äiti", "isä", "mummo", "pappa", "poika", "tyttö", "vesi", "maito",
           "leipä", "kirja", "koulu", "ystävä", "koira", "kissa", "talo", "ikkuna", "ehkä", "aina", "huomenna",
           "tänään", "puhua", "juoda", "syödä", "olla", "aika", "rakkaus", "aurinko", "kuu", "vuori", "joki",
           "meri", "metsä", "pieni", "iso", "punainen", "musta", "valkoinen", "moi", "mitä", "missä", "miksi",
           "paljon", "pöytä", "mökki", "sauna", "olut", "puu"),
    "ca": ("bon", "dia", "gràcies", "si", "us", "plau", "mare", "pare", "molt", "poc", "bonic", "platja",
           "poble", "món", "sempre", "mai", "demà", "avui", "pluja", "sol", "mar", "casa", "ciutat", "porta",
           "finestra", "parlar", "menjar", "beure", "viure", "amic", "amor", "temps", "cor", "paraula", "nen",
           "nena", "bé", "mal", "qui", "on", "per", "què", "pa", "peix", "vaca", "xocolata", "cotxe", "llibre",
           "fill", "mirall"),
}
# Latin-letter syllables every language here spells: each language says them its own way.
ONSETS = ("p", "b", "m", "f", "v", "t", "d", "n", "s", "z", "k", "g", "l", "r", "h", "w", "j", "ch", "sh", "pr",
          "bl", "pl", "br", "st", "tr", "sp", "mp", "")
NUCLEI = ("a", "e", "i", "o", "u", "a", "o", "ou", "ai", "ei", "au")
CODAS = ("", "", "", "m", "n", "s", "p", "t", "l", "r", "k")

# espeak-ng voice (language) per word list; the variants are voices (timbre, pitch, rhythm).
LANGUAGES = {"en": ("en-us", "en"), "de": ("de",), "fr": ("fr",), "es": ("es",), "it": ("it",),
             "pt": ("pt-br", "pt"), "nl": ("nl",), "pl": ("pl",)}
TRAIN_LANGUAGES = ("en", "de", "fr", "es", "it", "pt", "nl")
UNSEEN_LANGUAGES = ("pl",)  # measured apart: a language the drivers never heard
TRAIN_VARIANTS = ("m1", "m2", "m3", "m4", "m5", "m6", "f1", "f2", "f3", "klatt", "klatt2", "klatt3", "adam",
                  "Andy", "Annie", "steph", "max", "paul", "robert", "linda", "antonio", "Alicia", "benjamin",
                  "iven", "Lee", "quincy")
HELDOUT_VARIANTS = ("m7", "f4", "f5", "klatt4", "michel", "belinda")
RATE_WPM = (130, 215)
PITCH = (25, 75)
PITCH_RANGE = (20, 90)
WORD_GAP = (0, 3)

TRAIN_STREAM, HELDOUT_STREAM = 1, 2  # seed streams: a seed of one stream never draws a sentence of the other
NATURAL_STREAM = 3  # the festival and flite training sentences' stream
WORLD_STREAM = 4  # the stream of WORLD_FAMILY's training sentences
ALIGNED_STREAM = 5  # word-list sentences the aligner's cost is measured on (families.aligned_twins)

# English voices of other engines (festival.py, flite.py), by family: each voice's own mean pitch (Hz) centres the
# pitch drawn for it. flite's kal and kal16 are the CMU Kal diphones festival's kal is made of, so they are in no
# family: they would leak the held-out family into training.
ENGINES = ("espeak", "festival", "flite")
TRAIN_FAMILIES: dict[str, tuple[str, dict[str, float]]] = {
    "festival": ("festival", {"slt_hts": 170.0}),  # an HMM (HTS) voice
    "flite": ("flite", {"slt": 170.0, "awb": 110.0, "rms": 110.0}),  # statistical (clustergen) voices
}
HELDOUT_FAMILY = ("festival-diphone", "festival", {"kal": 105.0, "ked": 105.0})  # LPC diphone voices, never trained
# festival's voices of other languages (festival.WORLD_VOICES: diphone voices of eight people, a boy among them,
# and an HTS voice), each saying sentences of its own language: more speakers than English has with phone timings.
# Their pitch cannot be set (the own pitch here is only measured).
WORLD_FAMILY = ("festival-world", "festival", {"lp": 209.0, "pc": 120.0, "dita": 219.0, "krb": 254.0,
                                               "machac": 110.0, "ph": 110.0, "lj": 172.0, "mv": 110.0,
                                               "ona": 172.0})
# The other engines' voices that speak no English, and their language.
VOICE_LANGUAGES = {name: voice.language for name, voice in WORLD_VOICES.items()}
PITCH_OCTAVES = 0.25  # a voice's pitch drawn within +-this of its own mean


@dataclass(frozen=True)
class Spec:
    """One utterance to synthesise: its text and how it is spoken."""

    text: str
    language: str
    voice: str
    rate: int
    pitch: int
    pitch_range: int
    word_gap: int
    engine: str = "espeak"  # ENGINES: for festival and flite, `rate` sets the tempo and `pitch` the mean F0

    @property
    def tempo(self) -> float:
        """festival's and flite's duration factor of `rate` (175 words per minute: 1)."""
        return 175.0 / self.rate

    def pitch_hz(self, own_hz: float) -> float:
        """festival's and flite's target mean F0 of `pitch` (0..100, 50 the voice's own `own_hz`)."""
        return own_hz * 2.0 ** (PITCH_OCTAVES * (self.pitch - 50) / 25.0)


def pseudo_word(rng: np.random.Generator) -> str:
    """A random word of 1-3 syllables."""
    return "".join(str(rng.choice(ONSETS)) + str(rng.choice(NUCLEI)) + str(rng.choice(CODAS))
                   for _ in range(int(rng.integers(1, 4))))


def sentence(language: str, rng: np.random.Generator, pseudo_share: float = 0.3) -> str:
    """One or two random sentences in `language`: 3-9 words each, commas inside, . ? or ! at the end."""
    out = []
    for _ in range(int(rng.integers(1, 3))):
        words = [pseudo_word(rng) if rng.random() < pseudo_share else str(rng.choice(WORDS[language]))
                 for _ in range(int(rng.integers(3, 10)))]
        text = words[0][:1].upper() + words[0][1:]
        for k, word in enumerate(words[1:], 1):
            text += ("," if k > 1 and rng.random() < 0.18 else "") + " " + word
        out.append(text + str(rng.choice([".", ".", "?", "!"])))
    return " ".join(out)


def _spec(language: str, variants: tuple[str, ...], rng: np.random.Generator) -> Spec:
    voice = f"{rng.choice(LANGUAGES[language])}+{rng.choice(variants)}"
    return Spec(sentence(language, rng), language, voice, int(rng.integers(*RATE_WPM)), int(rng.integers(*PITCH)),
                int(rng.integers(*PITCH_RANGE)), int(rng.integers(WORD_GAP[0], WORD_GAP[1] + 1)))


def _family_spec(engine: str, voices: dict[str, float], rng: np.random.Generator, pseudo_share: float = 0.3
                 ) -> Spec:
    voice = str(rng.choice(sorted(voices)))
    language = VOICE_LANGUAGES.get(voice, "en")
    return Spec(sentence(language, rng, pseudo_share), language, voice, int(rng.integers(*RATE_WPM)),
                int(rng.integers(*PITCH)), 0, 0, engine)


def family_specs(count: int, seed: int, families: dict[str, tuple[str, dict[str, float]]] | None = None,
                 stream: int = NATURAL_STREAM, pseudo_share: float = 0.3) -> list[Spec]:
    """`count` utterances of other engines' voices (TRAIN_FAMILIES by default), the families in turn, sentences
    of `stream` in each voice's language (English but for VOICE_LANGUAGES), `pseudo_share` of their words
    pseudo-words."""
    families = TRAIN_FAMILIES if families is None else families
    rng = np.random.default_rng([stream, seed])
    order = sorted(families)
    return [_family_spec(*families[order[i % len(order)]], rng, pseudo_share) for i in range(count)]


def world_specs(count: int, seed: int) -> list[Spec]:
    """`count` training utterances of WORLD_FAMILY's voices, sentences of WORLD_STREAM."""
    return family_specs(count, seed, {WORLD_FAMILY[0]: WORLD_FAMILY[1:]}, stream=WORLD_STREAM)


def training_specs(count: int, seed: int) -> list[Spec]:
    """`count` training utterances: the training languages in turn, training voices."""
    rng = np.random.default_rng([TRAIN_STREAM, seed])
    return [_spec(TRAIN_LANGUAGES[i % len(TRAIN_LANGUAGES)], TRAIN_VARIANTS, rng) for i in range(count)]


def heldout_specs(count: int, seed: int, languages: tuple[str, ...] = TRAIN_LANGUAGES,
                  training: list[Spec] | None = None) -> list[Spec]:
    """`count` held-out utterances: held-out voices, sentences from the held-out stream (ValueError if one of
    them is also a sentence of `training`)."""
    rng = np.random.default_rng([HELDOUT_STREAM, seed])
    specs = [_spec(languages[i % len(languages)], HELDOUT_VARIANTS, rng) for i in range(count)]
    seen = {spec.text for spec in training or ()}
    repeated = [spec.text for spec in specs if spec.text in seen]
    if repeated:
        raise ValueError(f"held-out sentences also in training: {repeated[:3]}")
    return specs


__all__ = ["ENGINES", "HELDOUT_FAMILY", "HELDOUT_VARIANTS", "LANGUAGES", "Spec", "TRAIN_FAMILIES", "TRAIN_LANGUAGES",
           "TRAIN_VARIANTS", "UNSEEN_LANGUAGES", "VOICE_LANGUAGES", "WORDS", "WORLD_FAMILY", "family_specs",
           "heldout_specs", "pseudo_word", "sentence", "training_specs", "world_specs"]
