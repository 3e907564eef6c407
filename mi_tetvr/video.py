"""Videos: frames written as an H.264 MP4 (imageio-ffmpeg's encoder), which every player
reads; numpy only, no Mitsuba variant needed."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["write_video", "FPS"]

#: Frames per second of the project's videos (orbits, series, fly-throughs).
FPS = 24


def write_video(path, frames, fps: int = FPS) -> None:
    """Write 8-bit sRGB frames ``(n, h, w, 3)`` as an H.264 MP4 (yuv420p, which
    every player reads; odd sizes are padded by one pixel, black)."""
    with needs("vis", "writing a video"):
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
