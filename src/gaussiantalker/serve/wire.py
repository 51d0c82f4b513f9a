"""The live wire format, version 1: the drive message, the frame packet and the control messages that a served
session and its page exchange (docs/serve.md, "Wire format"). One definition: the browser's decoders read their
constants from web/src/generated.js, which is generated from `js_constants()` and refused when stale."""

from __future__ import annotations

import math

import numpy as np

from gaussiantalker.sdk.audio import to_pcm16
from gaussiantalker.sdk.binary_layout import field_layout, fields_struct

WIRE_VERSION = 1  # the version this module writes, in every drive message and frame packet

# -- the drive message ------------------------------------------------------------------------------------------
# One message per frame, little-endian: a 28-byte header, then `count` float32 values.
#   0  4s   magic b"GTLD"
#   4  u8   version (1)
#   5  u8   rig: 0 FLAME (values: expression[split], flame_pose[15], head_translation[3]),
#                1 ARKit (values: blendshapes[split] in ARKIT_BLENDSHAPES order, head_rotation[3], head_translation[3])
#   6  u8   flags: bit 0 speaking
#   7  u8   dtype: 0 float32 (the only one written)
#   8  u32  frame index
#   12 u32  epoch: barge-ins so far; drives of an older epoch at or past the first index of a newer one are stale
#   16 f64  pts (seconds on the session's audio clock, index / fps)
#   24 u16  count of values
#   26 u16  split: where the expression (FLAME) or the weights (ARKit) end; count - split is the pose (18 or 6)
DRIVE_MAGIC = b"GTLD"
DRIVE_VERSION = WIRE_VERSION
DRIVE_FIELDS = (("magic", "4s"), ("version", "B"), ("rig", "B"), ("flags", "B"), ("dtype", "B"), ("index", "I"),
                ("epoch", "I"), ("pts", "d"), ("count", "H"), ("split", "H"))
DRIVE_HEADER = fields_struct(DRIVE_FIELDS)
RIG_CODES = {"flame": 0, "arkit": 1}
POSE_VALUES = {0: 18, 1: 6}  # values after `split`: FLAME flame_pose + translation, ARKit rotation + translation
SPEAKING_FLAG = 1

# -- the frame packet (one WebSocket message per frame) ----------------------------------------------------------
#   0  4s   magic b"GTLF"
#   4  u8   version (1)
#   5  u8   audio dtype: 0 int16 PCM, mono, at the session's sample_rate (the only one written)
#   6  u16  reserved (0)
#   8  u32  drive_bytes: the length of the drive message that follows
#   12      the drive message, then the frame's audio (what is left: whole int16 samples, zeros while idle)
PACKET_MAGIC = b"GTLF"
PACKET_VERSION = WIRE_VERSION
PACKET_FIELDS = (("magic", "4s"), ("version", "B"), ("dtype", "B"), ("reserved", "H"), ("drive_bytes", "I"))
PACKET_HEADER = fields_struct(PACKET_FIELDS)

# -- control messages (JSON text) ---------------------------------------------------------------------------------
# The page's start message: {"source": one of START_SOURCES, "chunk_ms", "text", "mic_rate"}; the server's answer:
# {"session", "fps", "sample_rate", "start_time", "rig", "wire"}; later {"interrupted": {"epoch"}},
# {"interrupt": {"epoch", "index"}} and {"error": "one line"}. The page sends {"interrupt": true} or, with source
# mic, binary int16 PCM at mic_rate.
START_SOURCES = ("file", "text", "none", "mic")
CHUNK_MS_RANGE = (10, 10000)  # how the server pushes its own voice: chunk length, milliseconds
MIC_RATE_RANGE = (8000, 192000)  # the page's microphone PCM, Hz
INTERRUPT_MESSAGE = {"interrupt": True}

# WebSocket close codes the server uses (RFC 6455), each with a one-line reason.
CLOSE_GOING_AWAY = 1001  # the server drains (SIGTERM): reconnect elsewhere
CLOSE_POLICY = 1008  # the client broke a bound: it does not read, sends too fast, or sent what is not allowed
CLOSE_TRY_AGAIN = 1013  # refused for capacity (too many sessions); try again later or elsewhere


class DriveFormatError(ValueError):
    """A drive message or frame packet that is not one: truncated, lying about its count, or of an unknown kind."""


def encode_drive(index: int, pts: float, drive, speaking: bool, epoch: int = 0) -> bytes:
    """One frame's drive (a FrameDrive or BlendshapeDrive) as a drive message."""
    if hasattr(drive, "blendshapes"):
        rig, parts = RIG_CODES["arkit"], (drive.blendshapes, drive.head_rotation, drive.head_translation)
    else:
        rig, parts = RIG_CODES["flame"], (drive.expression, drive.flame_pose, drive.head_translation)
    values = np.concatenate(parts).astype("<f4")
    header = DRIVE_HEADER.pack(DRIVE_MAGIC, DRIVE_VERSION, rig, SPEAKING_FLAG if speaking else 0, 0, index, epoch,
                               float(pts), values.size, parts[0].size)
    return header + values.tobytes()


def decode_drive(message: bytes) -> dict:
    """A drive message -> {index, pts, epoch, speaking, rig ("flame"/"arkit"), values float32 [count], split};
    DriveFormatError naming what is wrong. Every count is checked against the bytes present."""
    data = bytes(message)
    if len(data) < DRIVE_HEADER.size:
        raise DriveFormatError(f"drive message truncated: {len(data)} bytes, the header alone is {DRIVE_HEADER.size}")
    magic, version, rig, flags, dtype, index, epoch, pts, count, split = DRIVE_HEADER.unpack_from(data)
    if magic != DRIVE_MAGIC:
        raise DriveFormatError(f"not a drive message (magic {magic!r}, expected {DRIVE_MAGIC!r})")
    if version != DRIVE_VERSION or dtype != 0:
        raise DriveFormatError(f"drive message version {version} dtype {dtype}: only version {DRIVE_VERSION} "
                               "float32 is read")
    if rig not in POSE_VALUES:
        raise DriveFormatError(f"drive message has unknown rig code {rig}")
    body = len(data) - DRIVE_HEADER.size
    if count * 4 != body:
        raise DriveFormatError(f"drive message claims {count} values ({count * 4} bytes) but carries {body} bytes")
    if split + POSE_VALUES[rig] != count:
        raise DriveFormatError(f"drive message splits {count} values at {split}: the pose needs {POSE_VALUES[rig]}")
    if not math.isfinite(pts) or pts < 0:
        raise DriveFormatError(f"drive message pts {pts} is not a finite time >= 0")
    values = np.frombuffer(data, "<f4", count, DRIVE_HEADER.size).astype(np.float32)
    if not np.isfinite(values).all():
        raise DriveFormatError("drive message has non-finite values")
    return {"index": index, "pts": pts, "epoch": epoch, "speaking": bool(flags & SPEAKING_FLAG),
            "rig": "arkit" if rig == RIG_CODES["arkit"] else "flame", "values": values, "split": split}


def encode_frame_packet(drive_message: bytes, audio: np.ndarray) -> bytes:
    """A frame packet: a drive message and the frame's audio (float in [-1, 1] or int16), as int16 PCM."""
    if audio.dtype != np.int16:
        audio = to_pcm16(audio)
    return PACKET_HEADER.pack(PACKET_MAGIC, PACKET_VERSION, 0, 0, len(drive_message)) + drive_message \
        + audio.astype("<i2", copy=False).tobytes()


# struct codes of the headers' fields as numpy's (little-endian, packed: the same bytes)
_NUMPY_CODES = {"4s": "S4", "B": "u1", "H": "<u2", "I": "<u4", "d": "<f8"}


def frame_packets(rig: str, indices: np.ndarray, pts: np.ndarray, values: np.ndarray, speaking: np.ndarray,
                  epochs: np.ndarray, audio: np.ndarray) -> np.ndarray:
    """Many frames' packets at once, each the bytes `encode_frame_packet(encode_drive(...), audio)` gives: a
    [R, packet bytes] uint8 array whose row k is frame k's packet (its drive message at PACKET_HEADER.size on), from
    the drives' values [R, count] (their fields in order) and audio [R, S] (float, or int16)."""
    count, samples = values.shape[1], audio.shape[1]
    drive_bytes = DRIVE_HEADER.size + 4 * count
    layout = np.dtype([(f"packet_{name}", _NUMPY_CODES[code]) for name, code in PACKET_FIELDS]
                      + [(f"drive_{name}", _NUMPY_CODES[code]) for name, code in DRIVE_FIELDS]
                      + [("values", "<f4", (count,)), ("audio", "<i2", (samples,))])
    packets = np.zeros(values.shape[0], layout)
    packets["packet_magic"], packets["packet_version"], packets["packet_drive_bytes"] = PACKET_MAGIC, PACKET_VERSION, \
        drive_bytes
    packets["drive_magic"], packets["drive_version"], packets["drive_rig"] = DRIVE_MAGIC, DRIVE_VERSION, RIG_CODES[rig]
    packets["drive_flags"] = np.where(speaking, SPEAKING_FLAG, 0)
    packets["drive_index"], packets["drive_epoch"], packets["drive_pts"] = indices, epochs, pts
    packets["drive_count"], packets["drive_split"] = count, count - POSE_VALUES[RIG_CODES[rig]]
    packets["values"] = values
    packets["audio"] = audio if audio.dtype == np.int16 else to_pcm16(audio)
    return packets.view(np.uint8).reshape(values.shape[0], -1)


def decode_frame_packet(message: bytes) -> dict:
    """A frame packet -> {"drive": decode_drive's dict, "audio": int16 samples}; DriveFormatError naming what is
    wrong. drive_bytes is checked against the bytes present before anything is read."""
    data = bytes(message)
    if len(data) < PACKET_HEADER.size:
        raise DriveFormatError(f"frame packet truncated: {len(data)} bytes, the header alone is {PACKET_HEADER.size}")
    magic, version, dtype, _, drive_bytes = PACKET_HEADER.unpack_from(data)
    if magic != PACKET_MAGIC:
        raise DriveFormatError("not a frame packet (bad magic)")
    if version != PACKET_VERSION or dtype != 0:
        raise DriveFormatError(f"frame packet version {version} audio dtype {dtype}: only version {PACKET_VERSION} "
                               "int16 is read")
    rest = len(data) - PACKET_HEADER.size
    if drive_bytes > rest:
        raise DriveFormatError(f"frame packet claims a {drive_bytes}-byte drive but carries {rest} bytes after its "
                               "header")
    audio_bytes = rest - drive_bytes
    if audio_bytes % 2:
        raise DriveFormatError(f"frame packet audio is {audio_bytes} bytes: not whole int16 samples")
    drive = decode_drive(data[PACKET_HEADER.size:PACKET_HEADER.size + drive_bytes])
    audio = np.frombuffer(data, "<i2", audio_bytes // 2, PACKET_HEADER.size + drive_bytes).astype(np.int16)
    return {"drive": drive, "audio": audio}


def js_constants() -> dict[str, object]:
    """What web/src/live.js reads of this format, by name (generated into web/src/generated.js)."""
    return {
        "WIRE_VERSION": WIRE_VERSION, "DRIVE_MAGIC": list(DRIVE_MAGIC), "DRIVE_VERSION": DRIVE_VERSION,
        "DRIVE_HEADER_BYTES": DRIVE_HEADER.size, "POSE_VALUES": {str(k): v for k, v in POSE_VALUES.items()},
        "RIG_CODES": RIG_CODES, "SPEAKING_FLAG": SPEAKING_FLAG, "PACKET_MAGIC": list(PACKET_MAGIC),
        "PACKET_VERSION": PACKET_VERSION, "FRAME_HEADER_BYTES": PACKET_HEADER.size,
        "DRIVE_LAYOUT": {name: list(span) for name, span in field_layout(DRIVE_FIELDS).items()},
        "PACKET_LAYOUT": {name: list(span) for name, span in field_layout(PACKET_FIELDS).items()},
        "START_SOURCES": list(START_SOURCES), "MIC_RATE_RANGE": list(MIC_RATE_RANGE),
        "CLOSE_GOING_AWAY": CLOSE_GOING_AWAY, "CLOSE_POLICY": CLOSE_POLICY, "CLOSE_TRY_AGAIN": CLOSE_TRY_AGAIN,
    }


__all__ = ["CHUNK_MS_RANGE", "CLOSE_GOING_AWAY", "CLOSE_POLICY", "CLOSE_TRY_AGAIN", "DRIVE_HEADER", "DRIVE_MAGIC",
           "DRIVE_VERSION", "DriveFormatError", "INTERRUPT_MESSAGE", "MIC_RATE_RANGE", "PACKET_HEADER", "PACKET_MAGIC",
           "PACKET_VERSION", "POSE_VALUES", "RIG_CODES", "SPEAKING_FLAG", "START_SOURCES", "WIRE_VERSION",
           "decode_drive", "decode_frame_packet", "encode_drive", "encode_frame_packet", "frame_packets",
           "js_constants"]
