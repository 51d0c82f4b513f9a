"""TalkingHead's names before its stages (docs/embedding.md, "Renamed names"): each keeps working for one release
and warns once per process (DeprecationWarning) with the name to use instead. The table is the list of them."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

from gaussiantalker.sdk.errors import SettingsError
from gaussiantalker.sdk.rig import ARKIT_RIG, check_drive_rig

from .compositor import check_composited_output
from .settings import BackendSettings

_warned: set[str] = set()


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """One DeprecationWarning per process for `old`, naming `new`."""
    if old in _warned:
        return
    _warned.add(old)
    warnings.warn(f"{old} is deprecated and goes in the next release: use {new} (docs/embedding.md, "
                  "\"Renamed names\")", DeprecationWarning, stacklevel=stacklevel)


def _flame_blocks(head) -> Callable:
    """The old `translate_blocks`: (expression, jaw) pairs for a FLAME speaker, weights for an ARKit one."""
    def translate_blocks(audio):
        for block in head.driver.translate_blocks(audio):
            yield block if head.driver.rig == ARKIT_RIG else (block[:, :-3], block[:, -3:])
    return translate_blocks


def _blendshape_drive(head) -> Callable:
    def blendshape_drive(weights=None, head_pose=None):
        check_drive_rig(head.driver.rig, ARKIT_RIG, "use render_params() or audio")
        return head.driver.drive(weights, head_pose)
    return blendshape_drive


def _composite_frame(head) -> Callable:
    def composite_frame(render, index):
        check_composited_output(head.compositor, "uint8")
        return head.compositor.frame(render, index)
    return composite_frame


def _motion_frames(head) -> Callable:
    def motion_frames(motion=None, head_pose=None, output="uint8"):
        return head.frames(head_pose=head_pose, output=output, motion=motion)
    return motion_frames


def _motion_drives(head) -> Callable:
    def motion_drives(motion=None, head_pose=None):
        return head.drives(head_pose=head_pose, motion=motion)
    return motion_drives


# Old TalkingHead attribute -> (what to use instead, how to get it from the head).
RENAMED_ATTRIBUTES: dict[str, tuple[str, Callable[[Any], Any]]] = {
    "graphs": ("head.frame_renderer.graphs", lambda head: head.frame_renderer.graphs),
    "splatter": ("head.frame_renderer.splatter", lambda head: head.frame_renderer.splatter),
    "background": ("head.frame_renderer.background", lambda head: head.frame_renderer.background),
    "scene": ("head.frame_renderer.scene", lambda head: head.frame_renderer.scene),
    "scene_guard": ("head.frame_renderer.scene_guard", lambda head: head.frame_renderer.scene_guard),
    "gaussians": ("head.frame_renderer.deform", lambda head: head.frame_renderer.deform),
    "prepare": ("head.frame_renderer.prepare", lambda head: head.frame_renderer.prepare),
    "draw": ("head.frame_renderer.draw", lambda head: head.frame_renderer.draw),
    "regions": ("head.frame_renderer.regions", lambda head: head.frame_renderer.regions),
    "region_weights": ("head.frame_renderer.region_weights", lambda head: head.frame_renderer.region_weights),
    "rig": ("head.driver.rig", lambda head: head.driver.rig),
    "config": ("head.driver.config (FLAME speakers)", lambda head: getattr(head.driver, "config", None)),
    "arkit": ("head.driver.arkit (ARKit speakers)", lambda head: getattr(head.driver, "arkit", None)),
    "pose_track": ("head.driver.pose_track", lambda head: head.driver.pose_track),
    "motion_track": ("head.driver.motion_track", lambda head: head.driver.motion_track),
    "silence_gate_dbfs": ("head.driver.silence_gate_dbfs", lambda head: head.driver.silence_gate_dbfs),
    "has_translator": ("head.driver.has_translator", lambda head: head.driver.has_translator),
    "load_audio": ("head.driver.load_audio", lambda head: head.driver.load_audio),
    "run_translator": ("head.driver.run_translator", lambda head: head.driver.run_translator),
    "translate": ("head.driver.translate", lambda head: head.driver.translate),
    "translate_blocks": ("head.driver.translate_blocks (blocks of [n, D] parameters)", _flame_blocks),
    "head_pose": ("head.driver.head_pose", lambda head: head.driver.head_pose),
    "frame_count": ("head.driver.frame_count", lambda head: head.driver.frame_count),
    "motion": ("head.driver.motion", lambda head: head.driver.motion),
    "blendshape_drive": ("head.driver.drive (ARKit speakers)", _blendshape_drive),
    "motion_frames": ("head.frames(motion=...)", _motion_frames),
    "motion_drives": ("head.drives(motion=...)", _motion_drives),
    "composite_frame": ("head.compositor.frame", lambda head: _composite_frame(head)),
    "composite": ("head.compositor is not None", lambda head: head.compositor is not None),
    "pipelined": ("head.backend_settings.pipeline is not False",
                  lambda head: head.backend_settings.pipeline is not False),
}


def renamed_attribute(head, name: str) -> Any:
    """An old name of `head`, warned once; AttributeError for a name that never was."""
    if name not in RENAMED_ATTRIBUTES:
        raise AttributeError(f"'TalkingHead' object has no attribute {name!r}")
    new, get = RENAMED_ATTRIBUTES[name]
    warn_renamed(f"TalkingHead.{name}", new, stacklevel=4)
    return get(head)


def settings_groups(render, output, backend, render_settings, output_settings, backend_settings) -> tuple:
    """(render_settings, output_settings, backend name or group) from the constructor's keywords: the old
    `render=`, `output=` and `backend=BackendSettings(...)` warn once and mean the new keywords."""
    def renamed(old_name: str, old, new_name: str, new):
        if old is None:
            return new
        if new is not None:
            raise SettingsError(f"{old_name}= and {new_name}= are one setting given twice; give {new_name}= only")
        warn_renamed(f"TalkingHead({old_name}=...)", f"{new_name}=...", stacklevel=5)
        return old

    render_settings = renamed("render", render, "render_settings", render_settings)
    output_settings = renamed("output", output, "output_settings", output_settings)
    if isinstance(backend, BackendSettings):
        backend_settings, backend = renamed("backend", backend, "backend_settings", backend_settings), None
    if backend_settings is not None and not isinstance(backend_settings, BackendSettings):
        raise SettingsError(f"backend_settings= must be a BackendSettings (or None), got "
                            f"{type(backend_settings).__name__}")
    if backend_settings is not None and backend is not None and backend != backend_settings.name:
        raise SettingsError(f"backend={backend!r} and backend_settings.name={backend_settings.name!r} are one setting "
                            "given twice with two values")
    return render_settings, output_settings, backend_settings if backend_settings is not None else (
        backend or "onnxruntime")


__all__ = ["RENAMED_ATTRIBUTES", "renamed_attribute", "settings_groups", "warn_renamed"]
