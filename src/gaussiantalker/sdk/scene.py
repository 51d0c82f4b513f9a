"""A deployment scene: the camera, head-pose range and driver a specialised bundle is compiled for (docs/scene.md).

The exporter reads one from a TOML or JSON file (`gt-export --scene`), leaves out what the scene never uses, and
stores the scene in the bundle; the runtime checks each drive and camera against it with `SceneGuard`, which warns
once per kind of departure and keeps rendering.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .camera import Camera
from .config import FLAME_JOINTS
from .errors import GaussianTalkerError

DRIVERS = ("audio", "flame")
BACKGROUND_MODES = ("color", "transparent")
# Joints besides the head's global rotation that a scene may let move (FLAME_JOINTS order, "global" excluded).
MOVABLE_JOINTS = FLAME_JOINTS[1:]
# Camera fields a scene may set; omitted ones come from the speaker's camera scaled to the scene's size.
CAMERA_FIELDS = ("fx", "fy", "cx", "cy", "R", "t", "near")
DEFAULT_EXPRESSION_SIGMA = 3.0
# Range checks allow this much beyond a bound (radians, metres, sigma): float32 round-trips of a bound pass.
RANGE_SLACK = 1e-5
# Camera fields count as the scene's when within this relative difference.
CAMERA_RTOL = 1e-6
# The most characters of a value a SceneError quotes: a refusal is one short line (docs/untrusted-input.md).
MAX_QUOTE = 80


class SceneError(GaussianTalkerError):
    """A scene description is unusable: a missing or unknown field, a range with lo > hi, a bad driver."""


class SceneRangeWarning(UserWarning):
    """A drive or camera lies outside the scene a bundle was specialised for (frames may show holes)."""


Range3 = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]


def _line(text: str, limit: int = MAX_QUOTE) -> str:
    """`text` on one line (whitespace collapsed), cut to `limit` characters."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _quote(value) -> str:
    """`value` as a SceneError quotes it: its repr on one line, at most MAX_QUOTE characters."""
    return _line(repr(value))


def _range3(name: str, value, *, unit: str) -> Range3:
    """Three (lo, hi) pairs with lo <= hi, finite, or SceneError naming the field."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        array = None
    if array is None or array.shape != (3, 2) or not np.all(np.isfinite(array)):
        raise SceneError(f"scene {name} must be three [lo, hi] pairs of finite numbers ({unit}, x y z), "
                         f"got {_quote(value)}")
    for axis, (lo, hi) in zip("xyz", array, strict=True):
        if lo > hi:
            raise SceneError(f"scene {name} {axis}: lo {lo:g} is above hi {hi:g}")
    return tuple((float(lo), float(hi)) for lo, hi in array)  # type: ignore[return-value]


def _no_unknown(section: str, data: dict, known: tuple[str, ...]) -> None:
    if not isinstance(data, dict):
        raise SceneError(f"scene [{section}] must be a table, got {type(data).__name__}")
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise SceneError(f"scene [{section}] has unknown field{'s' if len(unknown) > 1 else ''} "
                         f"{_line(', '.join(map(repr, unknown)))} (known: {', '.join(known)})")


@dataclass(frozen=True)
class Scene:
    """What a bundle will render: camera (size, and any intrinsics/pose that differ from the speaker's), the head's
    rotation (axis-angle components, degrees) and translation (metres) ranges, the driver, the joints that move
    (per-axis ranges in degrees; others stay at 0), the expression coefficients that may be non-zero (None: all)
    within +-expression_sigma, and the background."""

    width: int
    height: int
    camera: dict = field(default_factory=dict)
    rotation_deg: Range3 = ((-20.0, 20.0),) * 3
    translation_m: Range3 = ((-0.05, 0.05),) * 3
    driver: str = "audio"
    joints: dict = field(default_factory=lambda: {"jaw": ((-5.0, 30.0), (-5.0, 5.0), (-5.0, 5.0))})
    expression: tuple[int, ...] | None = None
    expression_sigma: float = DEFAULT_EXPRESSION_SIGMA
    background: str = "color"
    background_color: tuple[float, float, float] | None = None
    pose_from_track: bool = False

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 16384:
                raise SceneError(f"scene camera.{name} must be an integer in 1..16384, got {_quote(value)}")
        if not isinstance(self.camera, dict):
            raise SceneError(f"scene [camera] must be a table, got {type(self.camera).__name__}")
        unknown = sorted(set(self.camera) - set(CAMERA_FIELDS))
        if unknown:
            raise SceneError(f"scene [camera] has unknown field(s) {_line(', '.join(map(repr, unknown)))} "
                             f"(known: width, height, {', '.join(CAMERA_FIELDS)})")
        object.__setattr__(self, "rotation_deg", _range3("head.rotation_deg", self.rotation_deg, unit="degrees"))
        object.__setattr__(self, "translation_m", _range3("head.translation_m", self.translation_m, unit="metres"))
        if self.driver not in DRIVERS:
            raise SceneError(f"scene drive.driver must be one of {', '.join(DRIVERS)}, got {_quote(self.driver)}")
        if not isinstance(self.joints, dict):
            raise SceneError(f"scene [drive.joints] must be a table of joint = ranges, got {_quote(self.joints)}")
        bad = sorted(set(self.joints) - set(MOVABLE_JOINTS))
        if bad:
            raise SceneError(f"scene drive.joints names unknown joint(s) {_line(', '.join(map(repr, bad)))} (movable: "
                             f"{', '.join(MOVABLE_JOINTS)}; the global rotation is [head] rotation_deg)")
        joints = {name: _range3(f"drive.joints.{name}", value, unit="degrees")
                  for name, value in sorted(self.joints.items(), key=lambda kv: MOVABLE_JOINTS.index(kv[0]))}
        object.__setattr__(self, "joints", joints)
        if self.driver == "audio" and "jaw" not in joints:
            raise SceneError("scene drive.joints must include 'jaw' for driver = \"audio\" (the translator moves it)")
        if self.expression is not None:
            ids = self.expression
            if isinstance(ids, str) or not isinstance(ids, list | tuple | set | frozenset | range) or not all(
                    isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in ids):
                raise SceneError(f"scene drive.expression must be \"all\" or a list of coefficient indices >= 0, "
                                 f"got {_quote(ids)}")
            object.__setattr__(self, "expression", tuple(sorted(set(ids))))
        if not (isinstance(self.expression_sigma, int | float) and 0 < self.expression_sigma < 1e4):
            raise SceneError(f"scene drive.expression_sigma must be a number in (0, 1e4), got "
                             f"{_quote(self.expression_sigma)}")
        if self.background not in BACKGROUND_MODES:
            raise SceneError(f"scene background.mode must be one of {', '.join(BACKGROUND_MODES)}, got "
                             f"{_quote(self.background)}")
        if self.background_color is not None:
            color = np.asarray(self.background_color, dtype=np.float64) if _numeric(self.background_color) else None
            if color is None or color.shape != (3,) or not np.all((color >= 0) & (color <= 1)):
                raise SceneError(f"scene background.color must be three numbers in [0, 1], got "
                                 f"{_quote(self.background_color)}")
            object.__setattr__(self, "background_color", tuple(float(c) for c in color))

    # -- reading and writing -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict) -> Scene:
        """A scene from its file layout ([camera], [head], [drive], [drive.joints], [background])."""
        _no_unknown("scene", data, ("camera", "head", "drive", "background"))
        _no_unknown("camera", data.get("camera", {}), ("width", "height", *CAMERA_FIELDS))
        camera = dict(data.get("camera", {}))
        for name in ("width", "height"):
            if name not in camera:
                raise SceneError(f"scene [camera] needs {name} (pixels)")
        head = data.get("head", {})
        _no_unknown("head", head, ("rotation_deg", "translation_m", "from_track"))
        drive = data.get("drive", {})
        _no_unknown("drive", drive, ("driver", "joints", "expression", "expression_sigma"))
        background = data.get("background", {})
        _no_unknown("background", background, ("mode", "color"))
        expression = drive.get("expression", "all")
        if expression == "all":
            expression = None
        elif isinstance(expression, str):
            raise SceneError(f"scene drive.expression must be \"all\" or a list of indices, got {_quote(expression)}")
        defaults = cls(width=1, height=1)
        from_track = head.get("from_track", False)
        if not isinstance(from_track, bool):
            raise SceneError(f"scene head.from_track must be true or false, got {_quote(from_track)}")
        return cls(
            width=camera.pop("width"), height=camera.pop("height"), camera=camera,
            rotation_deg=head.get("rotation_deg", defaults.rotation_deg),
            translation_m=head.get("translation_m", defaults.translation_m),
            driver=drive.get("driver", "audio"), joints=drive.get("joints", defaults.joints),
            expression=expression, expression_sigma=drive.get("expression_sigma", DEFAULT_EXPRESSION_SIGMA),
            background=background.get("mode", "color"), background_color=background.get("color"),
            pose_from_track=from_track)

    def to_dict(self) -> dict:
        """The file layout, JSON-safe (what a bundle's manifest stores)."""
        background = {"mode": self.background}
        if self.background_color is not None:
            background["color"] = list(self.background_color)
        return {
            "camera": {"width": self.width, "height": self.height, **_plain(self.camera)},
            "head": {"rotation_deg": [list(r) for r in self.rotation_deg],
                     "translation_m": [list(r) for r in self.translation_m], "from_track": self.pose_from_track},
            "drive": {"driver": self.driver, "joints": {k: [list(r) for r in v] for k, v in self.joints.items()},
                      "expression": "all" if self.expression is None else list(self.expression),
                      "expression_sigma": self.expression_sigma},
            "background": background,
        }

    # -- what the scene allows -----------------------------------------------------------------------
    def resolve_camera(self, speaker_camera: Camera) -> Camera:
        """The scene's camera: the speaker's, scaled to the scene's size, with the scene's own fields applied."""
        base = speaker_camera.resized(self.width, self.height).to_dict()
        base.update(self.camera)
        return Camera.from_dict(base)

    def with_camera(self, camera: Camera) -> Scene:
        """This scene with every camera field explicit (what a bundle stores)."""
        explicit = {k: v for k, v in camera.to_dict().items() if k in CAMERA_FIELDS}
        return replace(self, width=camera.width, height=camera.height, camera=explicit)

    def with_pose_range(self, track: np.ndarray) -> Scene:
        """This scene with its head ranges set to the bounding box of a [T, 6] pose track (rotation in radians)."""
        track = np.asarray(track, dtype=np.float64).reshape(-1, 6)
        rotation = np.degrees(np.stack([track[:, :3].min(0), track[:, :3].max(0)], 1))
        translation = np.stack([track[:, 3:].min(0), track[:, 3:].max(0)], 1)
        return replace(self, rotation_deg=rotation.tolist(), translation_m=translation.tolist(),
                       pose_from_track=False)

    def joint_ranges_rad(self) -> np.ndarray:
        """[5, 3, 2] (lo, hi) per FLAME joint and axis in radians: the global rotation's, the moving joints', and
        (0, 0) for the joints that stay still."""
        ranges = np.zeros((len(FLAME_JOINTS), 3, 2))
        ranges[0] = np.radians(self.rotation_deg)
        for name, value in self.joints.items():
            ranges[FLAME_JOINTS.index(name)] = np.radians(value)
        return ranges

    def expression_allowed(self, n_expr: int) -> np.ndarray:
        """[n_expr] bool: the coefficients the scene lets be non-zero."""
        allowed = np.ones(n_expr, bool) if self.expression is None else np.zeros(n_expr, bool)
        if self.expression is not None:
            too_big = [i for i in self.expression if i >= n_expr]
            if too_big:
                raise SceneError(f"scene drive.expression lists coefficient {too_big[0]} but the speaker has "
                                 f"{n_expr} (indices 0..{n_expr - 1})")
            allowed[list(self.expression)] = True
        return allowed


def _numeric(value) -> bool:
    try:
        np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return False
    return True


def _plain(camera: dict) -> dict:
    return {k: (np.asarray(v).tolist() if k in ("R", "t") else float(v)) for k, v in camera.items()}


def load_scene(path: str | Path) -> Scene:
    """Read a scene file (.toml or .json); SceneError names the file and the problem."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the same parser as a package (a dependency there)
        import tomli as tomllib
    path = Path(path)
    kind = "JSON" if path.suffix.lower() == ".json" else "TOML"
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SceneError(f"cannot read scene file {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise SceneError(f"scene file {path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        data = json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except RecursionError:  # both parsers recurse on nested arrays and tables
        raise SceneError(f"scene file {path} is not valid {kind}: it nests too deep") from None
    except ValueError as exc:  # a decode error, or an integer past Python's 4,300-digit limit
        raise SceneError(f"scene file {path} is not valid {kind}: {_line(str(exc), 200)}") from None
    try:
        return Scene.from_dict(data)
    except SceneError as exc:
        raise SceneError(f"{path}: {exc}") from None


class SceneGuard:
    """Checks drives and cameras against a bundle's scene; each kind of departure warns once (SceneRangeWarning)."""

    def __init__(self, scene: Scene, n_expr: int) -> None:
        self.scene = scene
        self.ranges = scene.joint_ranges_rad()  # [5, 3, 2]
        self.translation = np.asarray(scene.translation_m)  # [3, 2]
        self.expression_allowed = scene.expression_allowed(n_expr)
        self.warned: set[str] = set()

    def _warn(self, kind: str, detail: str) -> None:
        if kind in self.warned:
            return
        self.warned.add(kind)
        warnings.warn(f"{detail}: outside the scene this bundle was specialised for (frames may show holes or "
                      f"wrong colours there; re-export without --scene or with a wider scene). Warned once per "
                      f"kind.", SceneRangeWarning, stacklevel=3)

    def check_drive(self, expression: np.ndarray, flame_pose: np.ndarray, head_translation: np.ndarray) -> None:
        """Warn (once per kind) when a frame's drive leaves the scene's ranges."""
        pose = np.asarray(flame_pose, np.float64).reshape(len(FLAME_JOINTS), 3)
        outside = (pose < self.ranges[..., 0] - RANGE_SLACK) | (pose > self.ranges[..., 1] + RANGE_SLACK)
        for joint, axis in zip(*np.nonzero(outside), strict=True):
            name = "head rotation" if joint == 0 else f"{FLAME_JOINTS[joint]} pose"
            lo, hi = np.degrees(self.ranges[joint, axis])
            self._warn(name, f"{name} {'xyz'[axis]} = {math.degrees(pose[joint, axis]):.2f}° is not in "
                             f"[{lo:g}, {hi:g}]°")
        translation = np.asarray(head_translation, np.float64).reshape(3)
        low, high = self.translation[:, 0] - RANGE_SLACK, self.translation[:, 1] + RANGE_SLACK
        for axis in np.flatnonzero((translation < low) | (translation > high)):
            lo, hi = self.translation[axis]
            self._warn("head translation", f"head translation {'xyz'[axis]} = {translation[axis]:.4f} m is not in "
                                           f"[{lo:g}, {hi:g}] m")
        expression = np.asarray(expression, np.float64).reshape(-1)
        fixed = np.flatnonzero(~self.expression_allowed[: expression.size] & (np.abs(expression) > RANGE_SLACK))
        if fixed.size:
            self._warn("expression", f"expression coefficient {fixed[0]} = {expression[fixed[0]]:.3g} (the scene "
                                     f"keeps it at 0)")
        sigma = self.scene.expression_sigma
        big = np.flatnonzero(np.abs(expression) > sigma + RANGE_SLACK)
        if big.size:
            self._warn("expression range", f"expression coefficient {big[0]} = {expression[big[0]]:.3g} is beyond "
                                           f"±{sigma:g}")

    def check_camera(self, camera: Camera) -> None:
        """Warn (once) when the camera is not the scene's (size, intrinsics or pose)."""
        scene_camera = self.scene.camera
        reference = {"width": self.scene.width, "height": self.scene.height, **scene_camera}
        actual = camera.to_dict()
        for name, value in reference.items():
            if not np.allclose(np.asarray(actual[name], np.float64), np.asarray(value, np.float64),
                               rtol=CAMERA_RTOL, atol=CAMERA_RTOL):
                self._warn("camera", f"camera {name} = {actual[name]!r} differs from the scene's {value!r}")
                return


__all__ = ["DRIVERS", "Scene", "SceneError", "SceneGuard", "SceneRangeWarning", "load_scene"]
