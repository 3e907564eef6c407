"""Orbits: frames around a mesh written as an MP4 video (imageio-ffmpeg's
H.264 encoder) and as a contact sheet (the frames on a grid)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["orbit_azimuths", "write_video", "contact_sheet", "FPS"]

#: Frames per second of an orbit video.
FPS = 24


def orbit_azimuths(start: float, frames: int) -> np.ndarray:
    """``frames`` azimuths (degrees) once around from ``start``."""
    if frames < 1:
        raise ValueError(f"an orbit needs at least one frame, got {frames}")
    return start + 360.0 * np.arange(frames) / frames


def write_video(path, frames, fps: int = FPS) -> None:
    """Write 8-bit sRGB frames ``(n, h, w, 3)`` as an H.264 MP4 (yuv420p, which
    every player reads; odd sizes are padded by one pixel, black)."""
    import imageio_ffmpeg
    frames = np.asarray(frames, np.uint8)
    n, h, w, _ = frames.shape
    H, W = h + h % 2, w + w % 2
    padded = np.zeros((n, H, W, 3), np.uint8)
    padded[:, :h, :w] = frames
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(str(path), (W, H), fps=fps, codec="libx264",
                                         pix_fmt_out="yuv420p", macro_block_size=1,
                                         output_params=["-crf", "18"])
    writer.send(None)
    for frame in padded:
        writer.send(np.ascontiguousarray(frame))
    writer.close()


def contact_sheet(frames, columns: int | None = None, gap: int = 2) -> np.ndarray:
    """The frames ``(n, h, w, c)`` on a grid of ``columns`` (default: about
    square), ``gap`` pixels apart on black."""
    frames = np.asarray(frames)
    n, h, w = frames.shape[:3]
    columns = columns or math.ceil(math.sqrt(n))
    rows = math.ceil(n / columns)
    sheet = np.zeros((rows * h + (rows - 1) * gap, columns * w + (columns - 1) * gap)
                     + frames.shape[3:], frames.dtype)
    for k, frame in enumerate(frames):
        r, c = divmod(k, columns)
        sheet[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = frame
    return sheet
