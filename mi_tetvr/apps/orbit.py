"""Orbits: the azimuths of frames around a mesh, and a contact sheet of
frames (on a grid); :mod:`mi_tetvr.video` writes them as an MP4 video."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["orbit_azimuths", "contact_sheet"]

def orbit_azimuths(start: float, frames: int) -> np.ndarray:
    """``frames`` azimuths (degrees) once around from ``start``."""
    if frames < 1:
        raise ValueError(f"an orbit needs at least one frame, got {frames}")
    return start + 360.0 * np.arange(frames) / frames


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
