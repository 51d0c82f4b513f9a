"""The tests' small speaker with a reference clip: a few frames of the demo clip at a small size and a random F
(the session's `clip_export` fixture builds it once; test_compositing and test_cli use it)."""

from __future__ import annotations

import copy

import torch

CLIP_FRAMES = 4
CLIP_SIZE = (96, 112)  # width, height


def make_clip_speaker(small_speaker):
    """A copy of `small_speaker` with a CLIP_FRAMES-frame CLIP_SIZE demo clip and a random F.
    Returns (speaker, the ClipComposer that rendered the clip)."""
    from gaussiantalker.exporter.demo.clip import ClipComposer, make_demo_clip
    from gaussiantalker.exporter.model.inpainter import InpainterNet

    speaker = copy.deepcopy(small_speaker)
    speaker.pose_track = speaker.pose_track[:CLIP_FRAMES].clone()
    composer = ClipComposer(speaker, size=CLIP_SIZE)
    speaker.reference = make_demo_clip(speaker, composer)
    torch.manual_seed(0)
    speaker.inpaint = InpainterNet().eval()
    # An untrained F is exactly its priors (its output layer starts at zero); a random output layer makes every
    # weight reach the composite, as a trained F's do.
    torch.nn.init.normal_(speaker.inpaint.head.weight, std=0.1)
    return speaker, composer
