"""Reading images: header sizes, decoding to float RGB, and pyramid downsampling."""

from __future__ import annotations

import itertools
import struct
import warnings
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np
import torch

__all__ = ["image_size", "read_rgb", "read_alpha", "read_mask", "downsample", "masked_downsample", "downsample_batch",
           "check_background", "may_have_alpha", "has_transparency", "uniform_border"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless, ...); C4, C8, CC are not frames.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _png_size(head: bytes) -> Optional[tuple[int, int]]:
    # IHDR is always the first chunk: 4-byte length, b"IHDR", width, height (big-endian).
    if len(head) >= 24 and head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return w, h
    return None


def _jpeg_size(f) -> Optional[tuple[int, int]]:
    if f.read(2) != b"\xff\xd8":
        return None
    while True:
        byte = f.read(1)
        while byte == b"\xff":  # markers may be padded with extra 0xFF bytes
            byte = f.read(1)
        if not byte:
            return None
        marker = byte[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            continue
        raw = f.read(2)
        if len(raw) < 2:
            return None
        (length,) = struct.unpack(">H", raw)
        if marker in _JPEG_SOF:
            data = f.read(5)
            if len(data) < 5:
                return None
            h, w = struct.unpack(">HH", data[1:5])
            return w, h
        f.seek(length - 2, 1)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header for PNG and JPEG.

    Other formats (or headers this parser does not understand) are decoded in full. Loaders call
    this for every image at load time, so size mismatches are reported before training starts
    without decoding hundreds of images.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    try:
        with open(path, "rb") as f:
            size = _png_size(f.read(24))
            if size is None:
                f.seek(0)
                size = _jpeg_size(f)
    except OSError as err:
        raise ValueError(f"cannot read image {path}: {err}") from None
    if size is not None and size[0] > 0 and size[1] > 0:
        return size
    arr = _decode(path)
    return arr.shape[1], arr.shape[0]


_WARNED_16_BIT = False


def _warn_16_bit_colour(path: Path) -> None:
    """Pillow, which skimage.io reads PNGs with, keeps 8 of the 16 bits of a colour PNG's
    channels (16-bit greyscale it reads whole): said once per process."""
    global _WARNED_16_BIT
    if _WARNED_16_BIT or path.suffix.lower() != ".png":
        return
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) == 26 and head[:8] == _PNG_SIGNATURE and head[24] == 16 and head[25] in (2, 4, 6):
        _WARNED_16_BIT = True
        warnings.warn(f"{path} is a 16-bit colour PNG: it is read at 8 bits per channel (the image reader's limit; "
                      "a 1/255 step, below what training resolves); further such images are not mentioned", stacklevel=4)


def _decode(path: Path) -> np.ndarray:
    import skimage.io

    _warn_16_bit_colour(path)
    keyed = _transparency_as_alpha(path) if path.suffix.lower() == ".png" else None
    if keyed is not None:
        return keyed
    try:
        arr = skimage.io.imread(str(path))
    except Exception as err:  # the imaging backends raise many unrelated types
        said = str(err).split("Based on the extension")[0].strip()  # not imageio's advice to install video plugins
        raise ValueError(f"cannot read image {path}: {said} (not an image file any installed reader decodes)") from None
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (1, 2, 3, 4)):
        raise ValueError(f"image {path} has unsupported shape {list(arr.shape)} "
                         "(expected [H,W], [H,W,1..4])")
    if arr.ndim == 3 and arr.shape[2] == 4:  # four channels are RGBA only if the file says so
        arr = _four_channels_as_rgb(path, arr)
    return arr


def _transparency_as_alpha(path: Path) -> Optional[np.ndarray]:
    """The file as RGBA (grey: LA) when its transparency is a tRNS chunk and not a channel: a
    palette PNG with alpha (what pngquant and Pillow's quantize write from RGBA renders), an RGB
    or grey PNG with a colour key; None for any other file. skimage.io decodes those to their
    colour alone, and the pixels they mark transparent would keep whatever colour was stored
    under them (black, as a rule), composited on no background and hidden from the silhouettes.
    Pillow parses the header chunks only (tRNS comes before the pixels), so the look is cheap."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            if "transparency" not in img.info or img.mode not in ("P", "RGB", "L"):
                return None
            return np.asarray(img.convert("LA" if img.mode == "L" else "RGBA"))
    except Exception:  # not a file Pillow opens: the other reader reports it
        return None


def _four_channels_as_rgb(path: Path, arr: np.ndarray) -> np.ndarray:
    """`arr` as decoded when the file's colour mode has an alpha channel (RGBA), else the file
    converted to RGB by Pillow: a CMYK JPEG (print and photo tools write them) decodes to four
    channels too, and taken as RGBA its K channel would become alpha."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            if img.mode in ("RGBA", "RGBa", "LA", "La", "PA"):
                return arr
            if img.mode == "CMYK":
                return np.asarray(img.convert("RGB"))
            mode = img.mode
    except Exception:  # Pillow cannot open what the other backend read: keep its RGBA reading
        return arr
    raise ValueError(f"image {path} has colour mode {mode!r} with four channels; expected RGB, RGBA or CMYK")


def _to_unit_float(arr: np.ndarray, path: Path) -> np.ndarray:
    """Integer images scaled by their dtype's maximum; float images taken as they are."""
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max)
    if np.issubdtype(arr.dtype, np.floating):
        out = arr.astype(np.float32)
        if not np.isfinite(out).all() or out.min() < 0 or out.max() > 1:
            raise ValueError(f"float image {path} must hold finite values in [0,1]")
        return out
    if arr.dtype == np.bool_:
        return arr.astype(np.float32)
    raise ValueError(f"image {path} has unsupported dtype {arr.dtype}")


def check_background(background) -> Optional[tuple[float, float, float]]:
    """None, or three finite floats in [0, 1]."""
    if background is None:
        return None
    try:
        bg = tuple(float(v) for v in background)
    except (TypeError, ValueError):
        raise ValueError(f"background must be 3 floats in [0,1] or None, got {background!r}") from None
    if len(bg) != 3 or not all(0.0 <= v <= 1.0 for v in bg):
        raise ValueError(f"background must be 3 floats in [0,1] or None, got {background!r}")
    return bg


def may_have_alpha(path: Path) -> bool:
    """Whether an image file may carry alpha, from its name and header (PNG colour types 4 and 6,
    or a tRNS chunk); JPEG never does, any other format counts as 'may'."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        return False
    if suffix != ".png":
        return True
    with open(path, "rb") as f:
        head = f.read(1 << 16)  # the header chunks; tRNS comes before the first IDAT
    end = head.find(b"IDAT")
    return len(head) < 26 or head[25] in (4, 6) or b"tRNS" in head[:end if end >= 0 else None]


def has_transparency(path: Path) -> bool:
    """Whether an image file has an alpha channel with a pixel below fully opaque (decoded to
    tell; call may_have_alpha first to skip files whose header has none)."""
    return read_alpha(path) is not None


# A rendered backdrop is one colour up to 8-bit rounding and JPEG's ringing (a few levels): a
# border pixel within this of the border's median colour (each channel) is the backdrop ...
# the image files the loaders that list a folder (LLFF, HyperNeRF) take, by suffix (any case)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
BORDER_TOLERANCE = 8.0 / 255.0
# ... and the border is uniform when this share of its pixels is (an object may reach the edge
# in some views; a photograph's border is many colours)
BORDER_SHARE = 0.9


def _border_pixels(x: torch.Tensor) -> torch.Tensor:
    """The one-pixel border of ``x`` [H, W, C] as [N, C] (every pixel of an image under 3 px
    high or wide)."""
    if x.shape[0] < 3 or x.shape[1] < 3:
        return x.reshape(-1, x.shape[2])
    return torch.cat([x[0], x[-1], x[1:-1, 0], x[1:-1, -1]])


def uniform_border(images: Iterable[torch.Tensor],
                   masks: Optional[Iterable[Optional[torch.Tensor]]] = None) -> Optional[tuple[float, float, float]]:
    """The colour of the images' one-pixel border when it is one colour, else None.

    ``images``: [H, W, 3] tensors. The per-channel median of every border pixel of every image,
    when at least BORDER_SHARE of those pixels lie within BORDER_TOLERANCE of it in every channel:
    the backdrop a synthetic scene without alpha was rendered or composited on. A photograph's
    border (sky, floor, walls) fails the test. ``masks``: optionally, per image, its pixel weights
    [H, W, 1] or None; border pixels a mask ignores (weight below 1/2) are left out."""
    rings = []
    for img, mask in zip(images, masks if masks is not None else itertools.repeat(None)):
        img = torch.as_tensor(img, dtype=torch.float32)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"uniform_border needs [H, W, 3] images, got {list(img.shape)}")
        pixels = _border_pixels(img)
        if mask is not None:
            weights = torch.as_tensor(mask, dtype=torch.float32).reshape(img.shape[0], img.shape[1], 1)
            pixels = pixels[_border_pixels(weights)[:, 0] >= 0.5]
        rings.append(pixels)
    if not sum(len(r) for r in rings):
        return None
    ring = torch.cat(rings)
    median = ring.median(dim=0).values
    close = ((ring - median).abs() <= BORDER_TOLERANCE).all(dim=1).float().mean()
    if float(close) < BORDER_SHARE:
        return None
    return tuple(float(c) for c in median.clamp(0.0, 1.0))


def read_rgb(path: Path, background: Optional[Sequence[float]] = None) -> torch.Tensor:
    """Decode an image to float32 [H, W, 3] in [0, 1], values linear in the file's values.

    Grayscale is repeated to three channels. With an alpha channel: composited as
    ``rgb * a + background * (1 - a)`` (straight alpha, as Blender writes it) when
    ``background`` is given, otherwise the alpha channel is dropped.
    """
    path = Path(path)
    arr = _to_unit_float(_decode(path), path)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    c = arr.shape[2]
    if c in (1, 2):
        color, alpha = np.repeat(arr[:, :, :1], 3, axis=2), (arr[:, :, 1:2] if c == 2 else None)
    else:
        color, alpha = arr[:, :, :3], (arr[:, :, 3:4] if c == 4 else None)
    bg = check_background(background)
    if alpha is not None and bg is not None:
        color = color * alpha + np.asarray(bg, dtype=np.float32) * (1.0 - alpha)
    return torch.from_numpy(np.ascontiguousarray(color, dtype=np.float32))


def read_alpha(path: Path) -> Optional[torch.Tensor]:
    """The alpha channel of an image file as float32 [H, W, 1] in [0, 1] (the weight
    :func:`read_rgb` composites its colour with), or None when the file has none or it is opaque
    everywhere (then it says nothing of where the content is)."""
    path = Path(path)
    arr = _to_unit_float(_decode(path), path)
    if arr.ndim != 3 or arr.shape[2] not in (2, 4) or not (arr[:, :, -1] < 1.0).any():
        return None
    return torch.from_numpy(np.ascontiguousarray(arr[:, :, -1:], dtype=np.float32))


def read_mask(path: Path) -> torch.Tensor:
    """Decode a mask image to float32 [H, W, 1]: 1 where a pixel counts, 0 where it is ignored.

    nerfstudio's convention (its ``mask_path``) and COLMAP's: any non-zero value keeps the pixel,
    zero drops it. Read as such: one channel; colour whose three channels are equal (masks saved
    as RGB); a palette image by its indices (index 0 drops, as nerfstudio reads it). A mask with
    an alpha channel is read from its grey or colour part while the alpha is constant, and from
    its alpha where only the alpha varies (a cut-out saved as white with transparent holes);
    where both vary and disagree it is refused, as is colour whose channels differ: neither
    says which pixels count.
    """
    path = Path(path)
    indices = _palette_indices(path)
    if indices is not None:
        return torch.from_numpy(np.ascontiguousarray(indices[:, :, None] != 0, dtype=np.float32))
    arr = _decode(path)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    c = arr.shape[2]
    grey = arr[:, :, :1] if c in (1, 2) else arr[:, :, :3]
    if grey.shape[2] == 3 and not ((grey[:, :, :1] == grey[:, :, 1:]).all()):
        raise ValueError(f"mask {path} is a colour image whose channels differ; a mask is one channel (or equal "
                         "RGB channels): non-zero keeps a pixel, zero ignores it")
    keep = np.asarray(grey[:, :, :1]) != 0
    if c in (2, 4):
        alpha = np.asarray(arr[:, :, -1:])
        if (alpha != alpha.flat[0]).any():  # the alpha says something
            by_alpha = alpha != 0
            if (grey[:, :, :1] == grey.flat[0]).all():
                keep = by_alpha
            elif (keep != by_alpha).any():
                raise ValueError(f"mask {path}: its grey values and its alpha channel both vary and disagree on "
                                 f"{int((keep != by_alpha).sum())} pixels; save the mask as one channel "
                                 "(non-zero keeps a pixel, zero ignores it)")
    return torch.from_numpy(np.ascontiguousarray(keep, dtype=np.float32))


def _palette_indices(path: Path) -> Optional[np.ndarray]:
    """[H, W] palette indices of a palette ("P") image, else None (the file is decoded as usual)."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            return np.asarray(img) if img.mode == "P" else None
    except Exception:  # not a file Pillow opens: _decode reports it
        return None


def masked_downsample(image: torch.Tensor, weights: torch.Tensor, resize) -> tuple[torch.Tensor, torch.Tensor]:
    """(the weighted mean of ``image`` [..., H, W, C] under ``weights`` [..., H, W, 1] (a mask) at
    the size ``resize`` makes, the weights at that size): resize(image x weights) /
    resize(weights), 0 where no weight reaches, and resize(weights). ``resize`` maps
    [..., H, W, C + 1] to the level (:func:`downsample` or :func:`downsample_batch` with the
    level's size), so an ignored pixel gives no colour to it."""
    both = resize(torch.cat([image * weights, weights], dim=-1))
    weight = both[..., -1:]
    mean = torch.where(weight > 1e-6, both[..., :-1] / weight.clamp_min(1e-6), torch.zeros_like(both[..., :-1]))
    return mean, weight


def downsample(image: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Resize [H, W, 3] to [height, width, 3] with an antialiasing filter.

    Uses ``skimage.transform.resize(order=1, anti_aliasing=True)``: a Gaussian prefilter with
    sigma = (s - 1) / 2 per axis (s = input/output size ratio) followed by linear interpolation.
    The geometry maps the full frame onto the full frame (output pixel centre i + 0.5 samples the
    input at (i + 0.5) * W / width), which is exactly what ``Camera.scaled`` assumes. Both
    filters have non-negative weights, so values stay in [0, 1].
    """
    from skimage.transform import resize

    if image.ndim != 3:
        raise ValueError(f"image must be [H,W,C], got {list(image.shape)}")
    if (image.shape[1], image.shape[0]) == (width, height):
        return image.clone()
    arr = image.detach().cpu().numpy().astype(np.float64)
    out = resize(arr, (height, width, arr.shape[2]), order=1, mode="symmetric",
                 anti_aliasing=True, preserve_range=True)
    return torch.from_numpy(np.ascontiguousarray(out, dtype=np.float32))


def _symmetric_index(n: int, pad: int, device) -> torch.Tensor:
    """Indices of a length-n axis padded by `pad` on each side with scipy's "reflect" rule
    (edge sample repeated: c b a | a b c | c b a), for any pad (repeats the reflection)."""
    idx = torch.arange(-pad, n + pad, device=device) % (2 * n)
    return torch.where(idx < n, idx, 2 * n - 1 - idx)


def _blur_axis(x: torch.Tensor, sigma: float, dim: int) -> torch.Tensor:
    """Gaussian filter along `dim` as scipy.ndimage.gaussian_filter1d (truncate 4, reflect)."""
    if sigma <= 0:
        return x
    radius = int(4.0 * sigma + 0.5)
    t = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (t / sigma) ** 2)
    w = (w / w.sum()).to(x.dtype).to(x.device)
    n = x.shape[dim]
    xp = x.index_select(dim, _symmetric_index(n, radius, x.device)).movedim(dim, -1)
    out = xp.unfold(-1, 2 * radius + 1, 1) @ w  # [..., n]
    return out.movedim(-1, dim)


def downsample_batch(images: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """:func:`downsample` for a batch [C, H, W, ch] (or [H, W, ch]) on its own device and dtype,
    in torch: the same Gaussian prefilter (sigma = (s - 1) / 2 per axis, truncated at 4 sigma,
    mirrored edges) and the same full-frame linear resampling (bilinear, pixel centres at +0.5),
    so a GPU loop's targets match the package's cached pyramid images to float32 rounding
    (tested against skimage). Any value range (the filter is linear with non-negative weights)."""
    import torch.nn.functional as F

    single = images.ndim == 3
    x = images[None] if single else images
    if x.ndim != 4:
        raise ValueError(f"images must be [C, H, W, ch] or [H, W, ch], got {list(images.shape)}")
    h0, w0 = x.shape[1], x.shape[2]
    if (w0, h0) == (width, height):
        return images.clone()
    dtype = x.dtype if x.dtype.is_floating_point else torch.float32
    x = x.to(dtype)
    x = _blur_axis(x, max(0.0, (h0 / height - 1) / 2), 1)
    x = _blur_axis(x, max(0.0, (w0 / width - 1) / 2), 2)
    out = F.interpolate(x.permute(0, 3, 1, 2), size=(height, width), mode="bilinear", align_corners=False)
    out = out.permute(0, 2, 3, 1).contiguous()
    return out[0] if single else out
