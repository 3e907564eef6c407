"""Images as the reconstruction sees them: premultiplied linear RGBA arrays,
read from and written to PNG/JPEG (sRGB, straight alpha) and EXR (linear,
premultiplied); area downscaling.

Photos are upright everywhere: a phone stores a portrait photo as landscape pixels with an EXIF
orientation tag, and every reader here (:func:`read_image`, :func:`image_size`,
:func:`upright_copy`) applies the tag, as image viewers do.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from mi_tetvr.color import linear_to_srgb, srgb_to_linear

from mi_tetvr.camera import check_factor
from mi_tetvr.extras import needs

__all__ = ["read_image", "write_image", "downscale_image", "image_size", "exif_orientation",
           "exif_focal_px", "upright_copy"]


_SRGB_LUT8 = srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)


#: EXIF orientations (tag 274) whose upright picture swaps width and height.
_TRANSPOSED = (5, 6, 7, 8)

#: The diagonal of a 36 x 24 mm frame, in mm: the 35 mm equivalent focal length is
#: defined on the diagonal (CIPA DC-008), so that it holds for any aspect ratio.
_FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))


def exif_orientation(im) -> int:
    """The EXIF orientation (1 - 8) of an open PIL image; 1 when absent or invalid."""
    try:
        o = int(im.getexif().get(0x0112, 1))
    except Exception:                    # a damaged EXIF block: no orientation
        return 1
    return o if 1 <= o <= 8 else 1


def image_size(path):
    """``(width, height)`` of an image file as shown upright, without decoding its pixels."""
    with needs("recon", "reading images"):
        from PIL import Image
    with Image.open(path) as im:
        w, h = im.size
        return (h, w) if exif_orientation(im) in _TRANSPOSED else (w, h)


def exif_focal_px(path):
    """The focal length in pixels of the upright picture from its EXIF data, or None.

    From the 35 mm equivalent focal length (tag 41989) over the frame's diagonal, else from the
    focal length in mm (tag 37386) and the focal plane's resolution (tags 41486/41488, scaled
    from the original picture's width, tag 40962, to this file's). Both are the camera's
    nominal values: a starting guess for structure from motion, which refines it.
    """
    with needs("recon", "reading images"):
        from PIL import Image
    with Image.open(path) as im:
        w, h = im.size
        try:
            ifd = im.getexif().get_ifd(0x8769)
        except Exception:
            return None
    f35 = _positive(ifd.get(41989))
    if f35 is not None:
        return f35 / _FULL_FRAME_DIAGONAL_MM * float(np.hypot(w, h))
    f_mm, res = _positive(ifd.get(37386)), _positive(ifd.get(41486))
    unit = {2: 25.4, 3: 10.0, 4: 1.0}.get(int(ifd.get(41488, 2) or 2))
    if f_mm is None or res is None or unit is None:
        return None
    original = _positive(ifd.get(40962))
    scale = max(w, h) / original if original and original >= max(w, h) else 1.0
    return f_mm * res / unit * scale


def _positive(value):
    try:
        v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if np.isfinite(v) and v > 0 else None


def upright_copy(src, dst) -> bool:
    """Copy a picture to ``dst`` turned upright by its EXIF orientation.

    The picture is decoded whole first, so that a damaged file raises here (``OSError``, as
    Pillow raises it) rather than later. A picture already upright is copied byte for byte; a
    turned one is written again (JPEG at quality 95 without chroma subsampling, others
    losslessly), with its other EXIF data (camera, focal length) kept and the orientation tag
    dropped. Returns whether it was turned.
    """
    with needs("recon", "reading images"):
        from PIL import Image, ImageOps
    with Image.open(src) as im:
        im.load()
        if exif_orientation(im) == 1:
            turned = None
        else:
            fmt = im.format
            turned = ImageOps.exif_transpose(im)
    if turned is None:
        shutil.copy2(src, dst)
        return False
    exif = turned.getexif()
    exif.pop(0x0112, None)
    options = dict(quality=95, subsampling=0) if fmt == "JPEG" else {}
    turned.save(dst, format=fmt, exif=exif.tobytes(), **options)
    return True


#: The largest transmittance an X-ray image may hold: above 1 only by photon
#: noise (a count above the beam's mean), kept so that noise stays unbiased.
MAX_TRANSMITTANCE = 2.0

def downscale_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Area-average an image by an integer factor.

    The right / bottom ``W % factor`` / ``H % factor`` pixels are cropped first (this keeps the
    image origin, so intrinsics scale by ``1 / factor`` exactly).

    Parameters
    ----------
    image : (H, W, C) float
    factor : int >= 1

    Returns
    -------
    (H // factor, W // factor, C) float32
    """
    factor = check_factor(factor)
    image = np.asarray(image, dtype=np.float32)
    if factor == 1:
        return image
    h, w = image.shape[0] // factor, image.shape[1] // factor
    if h == 0 or w == 0:
        raise ValueError(f"downscale factor {factor} is larger than the image {image.shape[:2]}")
    c = image.shape[2]
    crop = np.ascontiguousarray(image[:h * factor, :w * factor])
    # Rows first (contiguous blocks, fast), then columns of the 1/factor smaller array.
    rows = crop.reshape(h, factor, w * factor * c).sum(axis=1, dtype=np.float32)
    out = rows.reshape(h, w, factor, c).sum(axis=2, dtype=np.float32)
    out *= np.float32(1.0 / (factor * factor))
    return out


def read_image(path, downscale: int = 1) -> np.ndarray:
    """Read an image as premultiplied linear RGBA.

    PNG / JPEG (8 or 16 bit, grey, palette, RGB or RGBA) are sRGB with straight alpha: decoded to
    linear, then premultiplied, and turned upright by their EXIF orientation. EXR (and other
    HDR formats ``mitsuba.Bitmap`` reads) are linear and premultiplied (OpenEXR convention). A
    missing alpha channel is 1. ``.npy``: an (H, W) float array of X-ray transmittance
    ``T = I / I0``, read as what an absorbing volume renders: RGB 0 and alpha ``1 - T``.

    Parameters
    ----------
    path : str or Path
    downscale : int
        Integer area-averaging factor applied after premultiplication (see
        :func:`downscale_image`).

    Returns
    -------
    (H // downscale, W // downscale, 4) float32
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        t = np.load(path)
        if t.ndim != 2 or not np.issubdtype(t.dtype, np.floating):
            raise ValueError(f"{path}: an X-ray image is an (H, W) float array of "
                             f"transmittance, got {t.dtype} {t.shape}")
        # counted photons (Poisson noise) may exceed the unattenuated beam's mean
        if not np.all(np.isfinite(t)) or t.min() < 0 or t.max() > MAX_TRANSMITTANCE:
            raise ValueError(f"{path}: transmittance I/I0 must lie in [0, 1] (up to "
                             f"{MAX_TRANSMITTANCE:g} with photon noise), got "
                             f"[{np.nanmin(t):.4g}, {np.nanmax(t):.4g}]")
        img = np.zeros(t.shape + (4,), np.float32)
        img[..., 3] = 1.0 - t
        return downscale_image(img, downscale)
    if path.suffix.lower() in (".exr", ".hdr", ".pfm", ".rgbe"):
        import mitsuba as mi
        bmp = mi.Bitmap(str(path)).convert(mi.Bitmap.PixelFormat.RGBA, mi.Struct.Type.Float32,
                                           srgb_gamma=False)
        img = np.array(bmp, dtype=np.float32).reshape(bmp.height(), bmp.width(), 4)
        return downscale_image(img, downscale)

    with needs("recon", "reading images"):
        from PIL import Image, ImageOps
    with Image.open(path) as im:
        im.load()
        if exif_orientation(im) != 1:
            im = ImageOps.exif_transpose(im)
        mode = im.mode
        if mode in ("I;16", "I;16B", "I;16L", "I"):
            g = np.asarray(im, dtype=np.float64) / (65535.0
                                                    if mode != "I" or im.getextrema()[1] > 255
                                                    else 255.0)
            lin = srgb_to_linear(np.clip(g, 0, 1)).astype(np.float32)
            img = np.empty(lin.shape + (4,), np.float32)
            img[..., :3] = lin[..., None]
            img[..., 3] = 1.0
            return downscale_image(img, downscale)
        has_alpha = mode in ("RGBA", "LA", "PA", "La", "RGBa") or \
            (mode == "P" and "transparency" in im.info)
        target = "RGBA" if has_alpha else "RGB"
        arr = np.asarray(im if im.mode == target else im.convert(target))
    if has_alpha:
        img = np.take(_SRGB_LUT8, arr)                   # (H, W, 4); alpha fixed below
        img[..., 3] = arr[..., 3] * np.float32(1.0 / 255.0)
        img[..., :3] *= img[..., 3:4]
    else:
        img = np.empty(arr.shape[:2] + (4,), np.float32)
        img[..., :3] = np.take(_SRGB_LUT8, arr)
        img[..., 3] = 1.0
    return downscale_image(img, downscale)


def write_image(path, image: np.ndarray) -> None:
    """Write a premultiplied linear RGBA image.

    ``.exr``: linear, premultiplied, float32 (exact). ``.png``: 8-bit sRGB with straight alpha
    (color un-premultiplied where alpha > 0, 0 where alpha = 0). ``.jpg``: 8-bit sRGB composited
    over black, alpha dropped. ``.npy``: the transmittance ``1 - alpha`` as an (H, W) float32
    array (X-ray images; the color is dropped).

    Parameters
    ----------
    path : str or Path
    image : (H, W, 4) or (H, W, 3) float
    """
    path = Path(path)
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"expected an (H, W, 3|4) image, got shape {image.shape}")
    if image.shape[2] == 3:
        image = np.concatenate([image, np.ones(image.shape[:2] + (1,), np.float32)], axis=2)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        np.save(path, np.ascontiguousarray(1.0 - image[..., 3], np.float32))
        return
    if suffix == ".exr":
        import mitsuba as mi
        mi.Bitmap(np.ascontiguousarray(image), pixel_format=mi.Bitmap.PixelFormat.RGBA).write(
            str(path))
        return
    with needs("recon", "writing images"):
        from PIL import Image
    alpha = np.clip(image[..., 3:4], 0.0, 1.0)
    if suffix == ".png":
        with np.errstate(divide="ignore", invalid="ignore"):
            straight = np.where(alpha > 0, image[..., :3] / np.maximum(alpha, 1e-30), 0.0)
        rgb8 = np.round(linear_to_srgb(np.clip(straight, 0, 1)) * 255.0).astype(np.uint8)
        a8 = np.round(alpha * 255.0).astype(np.uint8)
        Image.fromarray(np.concatenate([rgb8, a8], axis=2), "RGBA").save(path, compress_level=3)
    elif suffix in (".jpg", ".jpeg"):
        rgb8 = np.round(linear_to_srgb(np.clip(image[..., :3], 0, 1)) * 255.0).astype(np.uint8)
        Image.fromarray(rgb8, "RGB").save(path, quality=95)
    else:
        raise ValueError(f"unsupported image format '{path.suffix}' (use .png, .exr or .jpg)")
