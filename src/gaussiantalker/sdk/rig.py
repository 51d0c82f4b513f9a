"""What drives a speaker's face: its rig (FLAME parameters, or the 52 ARKit blendshape weights) and how its
Gaussians follow the mesh (the paper's triangle binding, or LAM's vertex binding). docs/import.md.

A bundle records its rig in the manifest entry "rig"; a bundle without one is a FLAME speaker (every bundle made
before ARKit speakers existed). Drives say which rig they speak, and a mismatch is a DriveError naming both.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from .errors import DriveError

FLAME_RIG = "flame"
ARKIT_RIG = "arkit"
RIGS = (FLAME_RIG, ARKIT_RIG)

# The 52 ARKit blendshape names in the order LAM's motion files and this SDK's [52] arrays use (alphabetical,
# as LAM's audio-to-expression model writes them). Apple's ARFaceAnchor defines the names, not an order.
ARKIT_BLENDSHAPES = (
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff",
    "cheekSquintLeft", "cheekSquintRight", "eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight",
    "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight", "eyeLookUpLeft", "eyeLookUpRight",
    "eyeSquintLeft", "eyeSquintRight", "eyeWideLeft", "eyeWideRight", "jawForward", "jawLeft", "jawOpen", "jawRight",
    "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft", "mouthFrownRight", "mouthFunnel",
    "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthPressLeft", "mouthPressRight", "mouthPucker",
    "mouthRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthSmileLeft",
    "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight", "mouthUpperUpLeft", "mouthUpperUpRight",
    "noseSneerLeft", "noseSneerRight", "tongueOut",
)
ARKIT_COUNT = len(ARKIT_BLENDSHAPES)

# How a Gaussian follows the mesh (docs/numerics.md): "triangle" (paper §3.3.1: the parent triangle's frame moves,
# rotates and scales it), "scaled_triangle" (GaussianAvatars: the same frame, with the local position and scale in
# units of the triangle's size k) or "vertex" (LAM: a mesh vertex plus a fixed offset carried by the head bone).
TRIANGLE_BINDING = "triangle"
SCALED_TRIANGLE_BINDING = "scaled_triangle"
VERTEX_BINDING = "vertex"
BINDINGS = (TRIANGLE_BINDING, SCALED_TRIANGLE_BINDING, VERTEX_BINDING)
# The bindings of a FLAME speaker (Gaussians on mesh triangles).
TRIANGLE_BINDINGS = (TRIANGLE_BINDING, SCALED_TRIANGLE_BINDING)
# A vertex-bound Gaussian's covariance: "static" keeps its rest-pose covariance whatever the head does (what LAM's
# web renderer draws), "head" turns it with the head bone.
COVARIANCE_MODES = ("static", "head")


@dataclass(frozen=True)
class ArkitRig:
    """The manifest's "rig" of an ARKit speaker: blendshape names its drive holds, binding, timing."""

    blendshapes: tuple[str, ...] = ARKIT_BLENDSHAPES
    binding: str = "vertex"
    covariance: str = "static"
    fps: int = 30
    sample_rate: int = 16000
    kind: str = field(default=ARKIT_RIG)

    def __post_init__(self) -> None:
        object.__setattr__(self, "blendshapes", tuple(self.blendshapes))
        if self.kind != ARKIT_RIG:
            raise ValueError(f"an ArkitRig has kind {ARKIT_RIG!r}, got {self.kind!r}")
        unknown = [name for name in self.blendshapes if name not in ARKIT_BLENDSHAPES]
        if unknown or len(set(self.blendshapes)) != len(self.blendshapes) or not self.blendshapes:
            raise ValueError(f"rig blendshapes must be distinct ARKit names, got unknown {unknown[:3]}"
                             if unknown else "rig blendshapes must be a non-empty list of distinct ARKit names")
        if self.binding != VERTEX_BINDING:
            raise ValueError(f"an ARKit rig's binding is {VERTEX_BINDING!r}, got {self.binding!r}")
        if self.covariance not in COVARIANCE_MODES:
            raise ValueError(f"rig covariance must be one of {', '.join(COVARIANCE_MODES)}, got {self.covariance!r}")
        for name in ("fps", "sample_rate"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"rig {name} must be a positive int, got {value!r}")

    def to_dict(self) -> dict:
        data = asdict(self)
        data["blendshapes"] = list(self.blendshapes)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> ArkitRig:
        if not isinstance(data, dict):
            raise ValueError(f"rig must be a dict, got {type(data).__name__}")
        known = {"blendshapes", "binding", "covariance", "fps", "sample_rate", "kind"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown rig keys: {unknown}")
        return cls(**data)


def rig_kind(manifest: dict) -> str:
    """"flame" or "arkit": the rig a bundle's manifest records (none recorded: flame)."""
    rig = manifest.get("rig")
    if rig is None:
        return FLAME_RIG
    kind = rig.get("kind") if isinstance(rig, dict) else None
    if kind not in RIGS:
        raise ValueError(f"manifest 'rig' has kind {kind!r}; this SDK knows {', '.join(RIGS)}")
    return kind


def check_drive_rig(expected: str, given: str, hint: str = "") -> None:
    """DriveError when a drive of rig `given` is sent to a speaker of rig `expected`."""
    if expected != given:
        what = {FLAME_RIG: "FLAME parameters (render_params, FrameDrive, audio through its translator)",
                ARKIT_RIG: "the 52 ARKit blendshape weights (render_blendshapes, BlendshapeDrive, motion files)"}
        raise DriveError(f"this speaker is driven by {what[expected]}; a drive of {what[given]} cannot drive it"
                         + (f": {hint}" if hint else ""))


__all__ = ["ARKIT_BLENDSHAPES", "ARKIT_COUNT", "ARKIT_RIG", "ArkitRig", "BINDINGS", "COVARIANCE_MODES", "FLAME_RIG",
           "RIGS", "SCALED_TRIANGLE_BINDING", "TRIANGLE_BINDING", "TRIANGLE_BINDINGS", "VERTEX_BINDING",
           "check_drive_rig", "rig_kind"]
