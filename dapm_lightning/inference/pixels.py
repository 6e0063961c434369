"""Pixels for the network: any 8/16-bit image to RGB, the network size in each image's aspect, resizing."""

from __future__ import annotations

import math
import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dapm_lightning.inference.sources import permission_denied

SIZE_MULTIPLE = 32
"""The encoder's total stride: the shortest network input side, and what exported ONNX sizes are multiples of."""
DEFAULT_NETWORK_SIZE = (512, 512)
"""The network size for checkpoints that do not record their training size (the paper's 512 x 512)."""
MAX_UPSCALE = 4.0
"""An input enlarged more than this for the network is warned about (little detail to see)."""
MAX_PIXELS = 2 * 89_478_485
"""The most pixels an input image may have: what Pillow opens (twice ``PIL.Image.MAX_IMAGE_PIXELS``, above which it
refuses a decompression bomb; 100-megapixel mapping cameras are below it)."""

NetworkSize = tuple[int, int] | int | None
"""How big the network input is: ``(H, W)`` (the pixel count kept, each image's aspect), a width (height
from the aspect), or None (the image's own size, rounded)."""


def to_rgb8(image: np.ndarray, source: str = "image", *, bgr: bool = True) -> np.ndarray:
    """Any grey, grey+alpha, colour or colour+alpha image of 8 or 16 bits to ``[H, W, 3]`` uint8 RGB.

    ``bgr``: colour channels in OpenCV's order (as ``cv2.imread`` gives); False for RGB arrays.
    Anything else (float pixels, other channel counts) is refused with a message naming ``source``.
    """
    if image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"{source}: unsupported pixel type {image.dtype} (use 8- or 16-bit images)")
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3:
        raise ValueError(f"{source}: expected an [H, W] or [H, W, C] image, got shape {image.shape}")
    channels = image.shape[2]
    if channels == 1:
        return np.repeat(image, 3, axis=2)
    if channels == 2:
        return np.repeat(image[..., :1], 3, axis=2)  # grey + alpha
    if channels in (3, 4):
        return cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB) if bgr else np.ascontiguousarray(image[..., :3])
    raise ValueError(f"{source}: unsupported number of channels {channels}")


def network_size(height: int, width: int, target: NetworkSize, multiple: int = 1) -> tuple[int, int]:
    """The network input ``(h, w)`` for an ``height x width`` image, in the image's own aspect.

    ``target`` ``(H, W)``: about ``H * W`` pixels (a model trained on 64 x 64 images sees a 4000 x 3000 photo at
    74 x 55: the scale of what it learnt on). An int: that width. None: the image's own size. The short side is
    at least 32 pixels (the encoder's stride). The aspect is kept to the pixel, as the network's IGD and the
    FoV assume square pixels; ``multiple`` rounds both sides to a multiple (32 for an exported ONNX model),
    which bends the aspect slightly.
    """
    if target is None:
        scale = 1.0
    elif isinstance(target, int):
        scale = target / width
    else:
        scale = math.sqrt(target[0] * target[1] / (height * width))
    scale *= max(1.0, SIZE_MULTIPLE / (min(height, width) * scale))
    return (max(multiple, int(round(height * scale / multiple)) * multiple),
            max(multiple, int(round(width * scale / multiple)) * multiple))


def upscale_note(name: str, size: Sequence[int], net: Sequence[int]) -> str | None:
    """A warning when the network size enlarges an image more than :data:`MAX_UPSCALE` times."""
    factor = max(net[0] / size[0], net[1] / size[1])
    if factor <= MAX_UPSCALE:
        return None
    return (f"{name}: {size[1]}x{size[0]} pixels enlarged {factor:.0f}x to the network's {net[1]}x{net[0]}; "
            "predictions from so little detail are unreliable (give larger images)")


def prepare_image(rgb: np.ndarray, target: NetworkSize, multiple: int = 1) -> torch.Tensor:
    """``[H, W, 3]`` uint8 RGB -> ``[3, h, w]`` uint8 tensor at the network size."""
    size = network_size(rgb.shape[0], rgb.shape[1], target, multiple)
    if size != rgb.shape[:2]:
        shrink = size[0] < rgb.shape[0]
        rgb = cv2.resize(rgb, (size[1], size[0]), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))


def resize_images(images: Tensor, size: tuple[int, int]) -> Tensor:
    """``[B, 3, H, W]`` float images to ``size`` (antialiased bilinear).

    For float tensors given to the API and the exported model's sizes; 8-bit pixels go through
    :func:`prepare_image` (OpenCV) instead.
    """
    if tuple(images.shape[-2:]) == size:
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)


def read_image(path: Path) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB from any 8/16-bit grey, colour or RGBA image file (named in errors)."""
    if path.exists() and not os.access(path, os.R_OK):
        raise permission_denied(path)
    try:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as error:  # OpenCV refuses to decode more than CV_IO_MAX_IMAGE_PIXELS
        if "CV_IO_MAX_IMAGE_PIXELS" in str(error):
            raise too_large(path, "more pixels than OpenCV decodes (CV_IO_MAX_IMAGE_PIXELS)") from None
        raw = None
    if raw is None:
        raise ValueError(f"{path}: cannot be decoded as an image (damaged, cut short, or not an image)\n"
                         "Fix: replace it with an intact copy, or move it out of the source (predict has no option "
                         "to skip damaged images)")
    if jpeg_cut_short(path):
        warnings.warn(f"{path}: the JPEG stops before its end marker (cut short while copying?): the picture below "
                      "the cut is grey and its depth means nothing. Fix: copy the file again.", stacklevel=2)
    return to_rgb8(raw, str(path))


def too_large(path: Path, size: str) -> ValueError:
    """The error for an image of more than :data:`MAX_PIXELS` pixels (``size``: what its header claims)."""
    return ValueError(f"{path}: {size}, more than the {MAX_PIXELS:,} pixels predict reads (a damaged header, a "
                      "decompression bomb, or a huge mosaic)\nFix: downscale it or cut it into tiles below that size "
                      "(predict sees each image at its network size anyway)")


def jpeg_cut_short(path: Path) -> bool:
    """Whether a JPEG file (by its first bytes) lacks the end-of-image marker at its end.

    OpenCV decodes such a file, the missing rows grey, with no more than a libjpeg line on stderr naming no file.
    """
    with open(path, "rb") as stream:
        if stream.read(2) != b"\xff\xd8":
            return False
        stream.seek(0, 2)
        stream.seek(max(0, stream.tell() - 4096))
        tail = stream.read().rstrip(b"\x00\r\n\t ")  # padding some writers leave after the marker
    return not tail.endswith(b"\xff\xd9")


def image_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` of an image file from its header (Pillow reads no pixels), else by decoding it (formats Pillow lacks).

    Raises:
        ValueError: the header claims more than :data:`MAX_PIXELS` pixels (:func:`too_large`), or the file cannot
            be read or decoded (:func:`read_image`).
    """
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # below MAX_PIXELS: only the header read
            with Image.open(path) as image:
                height, width = int(image.height), int(image.width)
    except Image.DecompressionBombError as error:
        claimed = re.search(r"\((\d+) pixels\)", str(error))  # Pillow's message: "Image size (N pixels) exceeds..."
        raise too_large(path, f"{int(claimed[1]):,} pixels by its header" if claimed else "too large") from None
    except Exception:  # a format Pillow lacks (OpenCV may still read it), or a damaged file named by read_image
        height, width = read_image(path).shape[:2]
    if height * width > MAX_PIXELS:
        raise too_large(path, f"{width}x{height} pixels")
    return int(height), int(width)
