"""Image metrics on the sRGB scale, against numbers computed by hand."""
import math

import numpy as np
import pytest

from mi_tetvr.recon.metrics import display_rgb, image_metrics


def srgb(x):
    """IEC 61966-2-1 encoding of a linear value in (0.0031308, 1]."""
    return 1.055 * x ** (1 / 2.4) - 0.055


def test_psnr_on_srgb_pictures():
    # Opaque, uniform: linear 0.2 against 0.5 -> sRGB 0.48453 against 0.73536.
    pred = np.zeros((8, 6, 4))
    pred[..., :3], pred[..., 3] = 0.2, 1.0
    target = np.zeros((8, 6, 4))
    target[..., :3], target[..., 3] = 0.5, 1.0
    m = image_metrics(pred, target, None)
    d = srgb(0.5) - srgb(0.2)
    assert d == pytest.approx(0.25083, abs=1e-5)
    assert m["psnr"] == pytest.approx(-20 * math.log10(d), abs=1e-9)        # 12.01 dB
    assert m["psnr_linear"] == pytest.approx(-20 * math.log10(0.3), abs=1e-9)  # 10.46 dB
    assert m["mse"] == pytest.approx(d * d)


def test_background_and_alpha():
    # Premultiplied 0.1 with alpha 0.5 over white is 0.6; the target is white.
    pred = np.zeros((8, 8, 4))
    pred[..., :3], pred[..., 3] = 0.1, 0.5
    target = np.zeros((8, 8, 4))                      # empty: the background
    np.testing.assert_allclose(display_rgb(pred, [1, 1, 1]), srgb(0.6), atol=1e-12)
    m = image_metrics(pred, target, [1.0, 1.0, 1.0])
    assert m["psnr"] == pytest.approx(-20 * math.log10(1.0 - srgb(0.6)), abs=1e-9)
    # Over black the same render is 0.1 against 0; values above 1 are clipped.
    pred[0, 0, :3] = 3.0
    a = display_rgb(pred)
    assert a[0, 0, 0] == pytest.approx(1.0) and a[1, 1, 0] == pytest.approx(srgb(0.1))
    # One half of the pixels off by a constant: PSNR from the mean over all.
    half = target.copy()
    half[:4, ..., :3], half[:4, ..., 3] = 0.5, 1.0
    m = image_metrics(half, target, None)
    assert m["psnr"] == pytest.approx(-10 * math.log10(0.5 * srgb(0.5) ** 2), abs=1e-9)
    assert m["ssim"] < 1.0 and image_metrics(target, target, None)["ssim"] == pytest.approx(1.0)
    # Images smaller than SSIM's 7x7 window get a smaller one.
    assert image_metrics(half[:5, :5], target[:5, :5], None)["ssim"] < 1.0
