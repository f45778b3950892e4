"""Image files read for the scene (dome light and UsdUVTexture textures), as linear float32.

OpenImageIO reads the file; the source colour space follows UsdUVTexture's
``sourceColorSpace`` (:func:`load_image`).
"""
from __future__ import annotations

import numpy as np

from usdfiber.translators.mitsuba.errors import TranslationError

__all__ = ["load_image"]


def load_image(path: str, color_space: str = "auto", where: str = "") -> np.ndarray:
    """Read an image with OpenImageIO as linear float32 (H, W, C), row 0 = top.

    ``color_space`` follows UsdUVTexture ``sourceColorSpace``: ``raw`` keeps the values,
    ``sRGB`` decodes the sRGB transfer function on the colour channels (not alpha), ``auto``
    decodes when the file is 8-bit with 3 or 4 channels (the UsdPreviewSurface rule, as in
    Hydra's Hio). Raises :class:`TranslationError` naming ``where`` if it cannot be read.
    """
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(path)
    if buf.has_error:
        raise TranslationError(where or path, None, f"cannot read image {path!r}: {buf.geterror()}")
    spec = buf.spec()
    pixels = buf.get_pixels(oiio.FLOAT)
    if pixels is None or buf.has_error:
        raise TranslationError(where or path, None, f"cannot read image {path!r}: {buf.geterror()}")
    data = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    cs = color_space.lower()
    if cs == "auto":
        cs = "srgb" if spec.format.basetype == oiio.UINT8 and spec.nchannels in (3, 4) else "raw"
    if cs == "srgb":
        n = min(3, data.shape[2]) if data.shape[2] != 2 else 1
        c = data[..., :n]
        data[..., :n] = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    elif cs != "raw":
        raise TranslationError(where or path, None, f"unknown source colour space {color_space!r}")
    return data
