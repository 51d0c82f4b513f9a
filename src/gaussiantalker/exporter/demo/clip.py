"""A procedural reference clip for the demo speaker: what a filmed speaker's original video would hold.

Each frame is a textured background, the speaker's own render at the clip's pose and jaw (so the head region is
exactly what the Gaussians draw), and shoulders in front of the neck, moving with the head's sway. The facial
mask M is the head's silhouette in that frame, grown and feathered as a face parser's mask is, minus what the
shoulders hide. Training pairs for the inpainting generator F come from the same composer: the frame the clip
would have held with another jaw is the target (docs/compositing.md, "Demo clip").
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as nnf

from gaussiantalker.runtime.splat.gl import GLSplatter
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import FrameDrive, HeadPose
from gaussiantalker.sdk.image import to_uint8
from gaussiantalker.sdk.reference_clip import EncodedClip

from ..model.speaker import Speaker

CLIP_SIZE = (480, 600)  # width, height: a 4:5 portrait with the shoulders in it
CLIP_FOV_Y_DEG = 30.0  # wider than the bare-head camera (24 degrees) so the shoulders fit
HEAD_ROW = 0.42  # the head's centre sits at this fraction of the frame height
MASK_GROW_PX = 4  # the mask reaches this far past the silhouette (a parser's mask is never pixel-tight)
MASK_FEATHER_PX = 2  # then its edge is blurred over about this radius
JAW_OPEN_MAX = 0.28  # radians: the widest jaw of the clip's own speech


@dataclass(frozen=True)
class ClipFrame:
    """One composed clip frame: image float32 [H, W, 3], facial mask float32 [H, W], shoulders' alpha [H, W]."""

    image: np.ndarray
    mask: np.ndarray
    shoulders: np.ndarray


def clip_camera(speaker_camera: Camera, size: tuple[int, int] = CLIP_SIZE) -> Camera:
    """The clip's camera: the speaker camera's position and orientation, a wider portrait view, head above centre."""
    width, height = size
    focal = 0.5 * height / np.tan(np.radians(CLIP_FOV_Y_DEG) / 2.0)
    return Camera(width, height, focal, focal, width / 2.0, HEAD_ROW * height, speaker_camera.R, speaker_camera.t,
                  speaker_camera.near)


def clip_jaw_track(frames: int) -> np.ndarray:
    """[T] jaw opening (radians) of the clip's own speech: syllables at ~4 Hz with pauses."""
    t = np.arange(frames) / 25.0
    syllables = np.clip(np.sin(2 * np.pi * 4.1 * t), 0.0, None) ** 1.5
    phrases = np.clip(np.sin(2 * np.pi * 0.35 * t + 0.4) + 0.3, 0.0, 1.0)
    return (JAW_OPEN_MAX * syllables * phrases).astype(np.float32)


def _background(width: int, height: int) -> np.ndarray:
    """A static, textured room: vertical light gradient, a window, a shelf and fine plaster noise. [H, W, 3]"""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    u, v = x / width, y / height
    image = np.stack([0.62 + 0.10 * u, 0.60 + 0.06 * u, 0.55 - 0.05 * v], axis=-1)
    window = (np.abs(u - 0.16) < 0.11) & (np.abs(v - 0.30) < 0.20)
    image[window] = image[window] * 0.4 + np.array([0.78, 0.86, 0.95]) * 0.6
    shelf = (u > 0.74) & (np.abs(v - 0.36) < 0.012)
    image[shelf] = (0.35, 0.24, 0.15)
    for k in range(6):  # books on the shelf
        book = (np.abs(u - (0.78 + 0.035 * k)) < 0.012) & (v > 0.25 + 0.01 * (k % 3)) & (v < 0.348)
        image[book] = rng.uniform(0.2, 0.7, 3)
    noise = rng.normal(0.0, 1.0, (height // 4 + 1, width // 4 + 1, 1)).astype(np.float32)
    image += 0.012 * np.kron(noise, np.ones((4, 4, 1), np.float32))[:height, :width]
    return np.clip(image, 0.0, 1.0).astype(np.float32)


def _smooth_inside(distance: np.ndarray) -> np.ndarray:
    """Anti-aliased inside-ness of a signed distance in pixels (negative inside)."""
    return np.clip(0.5 - distance, 0.0, 1.0)


def _shoulders(camera: Camera, sway_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Shoulders and chest below the neck: alpha [H, W] and shaded shirt colour [H, W, 3]."""
    height, width = camera.height, camera.width
    y, x = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5
    metres_to_px = camera.fx / np.linalg.norm(camera.t)
    cx = camera.cx + sway_m * metres_to_px
    top = camera.cy + 0.112 * metres_to_px  # shoulder line, just above the render's neck cut
    half_width = 0.19 * metres_to_px
    # A rounded trapezoid: shoulders slope down from the neck, the chest fills the bottom of the frame.
    slope = np.clip((np.abs(x - cx) - 0.045 * metres_to_px) / half_width, 0.0, None)
    shoulder_top = top + 0.09 * metres_to_px * slope ** 1.3
    inside = np.minimum(y - shoulder_top, half_width * 1.4 - np.abs(x - cx))
    neckline = 0.03 * metres_to_px - np.hypot((x - cx) * 0.75, np.maximum(y - top, 0.0) * 1.4)
    alpha = _smooth_inside(-inside) * (1.0 - _smooth_inside(-neckline))
    shade = 0.8 + 0.2 * np.clip(1.0 - np.abs(x - cx) / half_width, 0.0, 1.0)
    colour = np.stack([0.16 * shade, 0.25 * shade, 0.42 * shade], axis=-1)
    return alpha.astype(np.float32), colour.astype(np.float32)


def _grow_and_feather(silhouette: np.ndarray) -> np.ndarray:
    """Binary silhouette [H, W] -> mask grown by MASK_GROW_PX and blurred over ~MASK_FEATHER_PX, in [0, 1]."""
    work = torch.from_numpy(silhouette.astype(np.float32))[None, None]
    grow = 2 * MASK_GROW_PX + 1
    # A square max filter is a row max then a column max: the same values, ~4x less work than the 2D window.
    work = nnf.max_pool2d(work, (1, grow), stride=1, padding=(0, MASK_GROW_PX))
    work = nnf.max_pool2d(work, (grow, 1), stride=1, padding=(MASK_GROW_PX, 0))
    blur = 2 * MASK_FEATHER_PX + 1
    work = nnf.avg_pool2d(nnf.pad(work, (MASK_FEATHER_PX,) * 4, mode="replicate"), blur, stride=1)
    return work[0, 0].numpy().clip(0.0, 1.0)


class ClipComposer:
    """Renders the demo speaker at clip poses and composes clip frames (used for the clip and for F's data)."""

    def __init__(self, speaker: Speaker, splatter: GLSplatter | None = None, size: tuple[int, int] = CLIP_SIZE
                 ) -> None:
        if speaker.pose_track is None:
            raise ValueError("the demo clip follows the speaker's pose track; this speaker has none")
        self.speaker = speaker
        self.camera = clip_camera(speaker.camera, size)
        self.splatter = splatter or GLSplatter()
        self.track = speaker.pose_track.numpy()
        self.jaw = clip_jaw_track(len(self.track))
        self.background = _background(self.camera.width, self.camera.height)

    def drive(self, index: int, jaw: float) -> FrameDrive:
        """Clip frame `index`'s head pose with the given jaw opening (radians) and a neutral expression."""
        row = self.track[index]
        return FrameDrive.make(self.speaker.config.n_expr, jaw_pose=[jaw, 0.0, 0.0],
                               head_pose=HeadPose.make(row[:3], row[3:]))

    @torch.no_grad()
    def render_head(self, drive: FrameDrive) -> np.ndarray:
        """The speaker's own render at the clip camera: premultiplied (C, 1 - T) float32 [H, W, 4]."""
        inputs = {k: torch.from_numpy(v) for k, v in drive.graph_inputs().items()}
        center = torch.from_numpy(self.camera.center.astype(np.float32))[None]
        means, cov3d, rgb, opacity = self.speaker.deform(inputs["expression"], inputs["flame_pose"],
                                                         inputs["head_translation"], center)
        return self.splatter.render(means[0].numpy(), cov3d[0].numpy(), rgb[0].numpy(), opacity.numpy(),
                                    self.camera, (0.0, 0.0, 0.0), output="rgba_float")

    def compose(self, index: int, head: np.ndarray) -> ClipFrame:
        """Clip frame `index` with `head` (premultiplied render) in it: background, head, shoulders in front."""
        alpha, shirt = _shoulders(self.camera, float(self.track[index, 3]))
        under = head[..., :3] + (1.0 - head[..., 3:4]) * self.background
        image = alpha[..., None] * shirt + (1.0 - alpha[..., None]) * under
        mask = _grow_and_feather(head[..., 3] >= 0.5) * (1.0 - alpha)
        return ClipFrame(image.astype(np.float32), mask.astype(np.float32), alpha)

    def frame(self, index: int, jaw: float | None = None) -> tuple[ClipFrame, np.ndarray]:
        """Clip frame `index` (with its own jaw unless `jaw` is given) and the head render in it."""
        head = self.render_head(self.drive(index, float(self.jaw[index]) if jaw is None else jaw))
        return self.compose(index, head), head

    def frames(self) -> Iterator[ClipFrame]:
        """Every clip frame, in order, with the clip's own jaw."""
        for index in range(len(self.track)):
            yield self.frame(index)[0]


def make_demo_clip(speaker: Speaker, composer: ClipComposer | None = None) -> EncodedClip:
    """The demo speaker's reference clip, encoded (one JPEG frame and one PNG mask per pose-track row)."""
    composer = composer or ClipComposer(speaker)
    frames = list(composer.frames())
    return EncodedClip.from_arrays((to_uint8(f.image) for f in frames), (f.mask for f in frames), composer.camera)
