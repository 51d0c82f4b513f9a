"""Speaker model configuration shared by the exporter (builds the torch speaker) and the runtime (reads the bundle).

Plain dataclasses of numbers so they round-trip through a weights-only checkpoint and a JSON manifest.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from .rig import TRIANGLE_BINDINGS

# FLAME joint order (kinematic tree: global is the root, neck its child, jaw and eyes children of the neck).
FLAME_JOINTS = ("global", "neck", "jaw", "left_eye", "right_eye")
FLAME_PARENTS = (-1, 0, 1, 1, 1)
# Full FLAME pose vector: one axis-angle triple per joint, in FLAME_JOINTS order.
POSE_DIM = 3 * len(FLAME_JOINTS)
# The latent-pose MLP sees every pose triple except the global (head) rotation: neck, jaw, eyes.
LATENT_POSE_INPUT_DIM = POSE_DIM - 3
# Audio is framed so that one video frame is exactly this many encoder features (50 Hz features, 25 fps video).
FEATURES_PER_FRAME = 2
# The speaker's timing unless its config says otherwise: 16 kHz audio (what the translator's encoder is built
# for), 25 video frames per second.
DEFAULT_SAMPLE_RATE = 16000
DEFAULT_FPS = 25
# The translator normalises each utterance to zero mean, unit variance: x / sqrt(var + AUDIO_NORM_EPS). 1e-5
# rather than wav2vec 2.0's 1e-7, so near-silent input (RMS << 3e-3) is not amplified to full scale.
AUDIO_NORM_EPS = 1e-5


@dataclass
class TranslatorConfig:
    """Sizes of the Motion Translator (wav2vec 2.0-style encoder + identity embedding + motion decoder)."""

    conv_channels: int = 64  # channels of every layer of the convolutional feature encoder
    conv_strides: tuple[int, ...] = (5, 2, 2, 2, 2, 2, 2)  # product = 320 samples per feature at 16 kHz
    encoder_dim: int = 64
    encoder_layers: int = 2
    encoder_heads: int = 4
    encoder_ffn: int = 128
    pos_conv_kernel: int = 16  # wav2vec 2.0 convolutional relative positional embedding (128 in the paper's)
    pos_conv_groups: int = 8
    decoder_dim: int = 64
    decoder_layers: int = 2
    decoder_heads: int = 4
    decoder_ffn: int = 128
    n_speakers: int = 4

    @property
    def samples_per_feature(self) -> int:
        """Audio samples per encoder feature: the product of the conv strides (320 by default)."""
        product = 1
        for stride in self.conv_strides:
            product *= stride
        return product

    @property
    def samples_per_frame(self) -> int:
        """Audio samples the translator consumes per video frame: FEATURES_PER_FRAME features (640 by default)."""
        return self.samples_per_feature * FEATURES_PER_FRAME


@dataclass
class SpeakerConfig:
    """Everything that fixes a speaker's tensor shapes and timing."""

    n_shape: int = 20
    n_expr: int = 20
    sh_degree: int = 3
    fps: int = DEFAULT_FPS
    sample_rate: int = DEFAULT_SAMPLE_RATE
    speaker_id: int = 0
    latent_dim: int = 8  # dimension of gamma = W_gamma(psi), the rank of the speaker-specific blendshapes
    latent_hidden: int = 64
    translator: TranslatorConfig = field(default_factory=TranslatorConfig)
    # How the Gaussians follow their triangles: "triangle" (the paper's frame) or "scaled_triangle" (GaussianAvatars';
    # sdk/rig.py TRIANGLE_BINDINGS, docs/numerics.md).
    binding: str = "triangle"
    # Names of the expression coefficients where the basis has named parts (the demo speaker's local fields; empty
    # for an unnamed basis such as a tracked FLAME one): live sessions find the speaker's blink here (docs/live.md).
    expression_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        self.expression_names = tuple(str(name) for name in self.expression_names)
        if self.expression_names and len(self.expression_names) != self.n_expr:
            raise ValueError(f"{len(self.expression_names)} expression_names for {self.n_expr} "
                             "expression coefficients")
        if self.binding not in TRIANGLE_BINDINGS:
            raise ValueError(f"speaker binding must be one of {', '.join(TRIANGLE_BINDINGS)}, got {self.binding!r}")

    @property
    def samples_per_frame(self) -> int:
        """Audio samples per video frame: the translator's (`TranslatorConfig.samples_per_frame`), the one
        definition; `check_timing` proves it equals sample_rate / fps."""
        return self.translator.samples_per_frame

    def check_timing(self) -> None:
        """ValueError unless sample_rate / fps is exactly the translator's samples per video frame.

        The translator turns every `samples_per_frame` samples into one frame; if that is not 1 / fps seconds of
        audio at `sample_rate`, video and audio drift apart (and onnxruntime fails on the length).
        """
        spf = self.translator.samples_per_frame
        if self.fps < 1 or self.sample_rate != spf * self.fps:
            strides = " x ".join(str(s) for s in self.translator.conv_strides)
            raise ValueError(
                f"config timing disagrees: sample_rate {self.sample_rate} / fps {self.fps} = "
                f"{self.sample_rate / max(self.fps, 1):.4g} samples per video frame, but the translator consumes "
                f"{spf} (conv strides {strides} = {self.translator.samples_per_feature} samples per feature, "
                f"{FEATURES_PER_FRAME} features per frame); use fps {self.sample_rate / spf:.4g} or matching strides")

    def to_dict(self) -> dict:
        data = asdict(self)
        data["translator"]["conv_strides"] = list(self.translator.conv_strides)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> SpeakerConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown speaker config keys: {sorted(unknown)}")
        values = dict(data)
        tr = dict(values.pop("translator", {}))
        if "conv_strides" in tr:
            tr["conv_strides"] = tuple(int(s) for s in tr["conv_strides"])
        return cls(translator=TranslatorConfig(**tr), **values)
