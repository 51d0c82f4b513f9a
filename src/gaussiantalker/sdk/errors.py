"""The SDK's own exception types: every user-facing failure is one of these, with a message naming the problem."""


class GaussianTalkerError(Exception):
    """Base class of every error the SDK raises on purpose."""


class BundleError(GaussianTalkerError):
    """A `.gtb` bundle is unreadable: truncated, corrupt, wrong version, or inconsistent with its manifest."""


class CheckpointError(GaussianTalkerError):
    """A `speaker.ckpt` is unreadable, unsafe (would run code) or missing/mis-shaped entries."""


class AudioError(GaussianTalkerError):
    """Audio input cannot be used (empty, non-finite, unreadable file, unsupported layout)."""


class CameraError(GaussianTalkerError):
    """A camera is invalid (non-positive size or focal length, non-finite values, non-rotation R)."""


class DriveError(GaussianTalkerError):
    """Per-frame drive parameters (FLAME expression/pose, head pose) have the wrong shape or non-finite values."""


class RenderError(GaussianTalkerError):
    """The OpenGL splatter cannot run: no context could be created, or a shader failed to compile."""


class SettingsError(RenderError, ValueError):
    """A TalkingHead setting is invalid, or given twice with two values (a shortcut keyword and a settings group);
    a RenderError (what bad render settings always raised) and a ValueError."""


class VideoError(GaussianTalkerError):
    """A video cannot be written: bad output path or folder, unknown format, codec or setting, encoder failure."""


class ImportFormatError(GaussianTalkerError):
    """An avatar file to import (docs/import.md) is missing a member or field, or holds one of the wrong shape."""


class LiveError(GaussianTalkerError):
    """A live session was used wrongly: audio pushed after end() or close(), more audio queued than the session
    holds (a consumer that stopped reading), frames() read twice at once, or a bad session setting."""
