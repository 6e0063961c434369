"""The contact sheet: under column headings, per image ``image and horizon | depth | sky | pose``, columns aligned.

Picture tiles are bounded for any aspect; each depth tile is in its image's own range, written on it in metres.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from dapm_lightning.data.pictures import depth_colours, depth_range
from dapm_lightning.geometry.camera import horizon_segment
from dapm_lightning.inference.postprocess import Prediction

CONTACT_TILE = 160
"""Height in pixels of one contact-sheet row."""
CONTACT_MAX_ASPECT = 4
"""A contact-sheet picture tile is at most this many times as wide as high, and at least a quarter of its
height wide: images of other aspects are letter-boxed, so a 10 x 30000 image's tile is 640 x 160, not 480000 x 160."""
CONTACT_MAX_IMAGES = 64
"""The most images a contact sheet shows (a sheet stays under about 25 Mpx, ~70 MB in memory)."""
CONTACT_HEADING = 28
"""Height in pixels of the column headings."""
CONTACT_COLUMNS = ("image, horizon", "depth (own range)", "sky", "pose")

def contact_tile(height: int, width: int, tile: int = CONTACT_TILE) -> tuple[int, int, int, int, int, int]:
    """Where an ``height x width`` picture goes in its contact-sheet tile.

    The tile is ``tile`` pixels high and the picture's own aspect wide, bounded to between a quarter and
    :data:`CONTACT_MAX_ASPECT` times its height; a picture of another aspect is shrunk to fit and centred.
    Returns ``(tile_w, tile_h, w, h, left, top)``: the tile's size, the picture's size and offset in it.
    """
    natural = max(1, round(width * tile / height))
    tile_w = min(max(natural, max(1, tile // CONTACT_MAX_ASPECT)), CONTACT_MAX_ASPECT * tile)
    if tile_w == natural:
        return tile_w, tile, tile_w, tile, 0, 0
    scale = min(tile_w / width, tile / height)
    w, h = max(1, min(tile_w, round(width * scale))), max(1, min(tile, round(height * scale)))
    return tile_w, tile, w, h, (tile_w - w) // 2, (tile - h) // 2


def _text(picture: np.ndarray, line: str, at: tuple[int, int], colour: tuple[int, int, int] = (0, 0, 0)) -> None:
    cv2.putText(picture, line, at, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)


def contact_tiles(prediction: Prediction, tile: int = CONTACT_TILE) -> list[np.ndarray]:
    """``[image, depth, sky, pose]`` tiles for one prediction (its ``rgb``, grey without), ``tile`` pixels high.

    The horizon of the pose used is drawn on the image, the depth range written on the depth, the pose (with each
    component's source other than the network) on the last tile. Each picture tile is at most
    :data:`CONTACT_MAX_ASPECT` times ``tile`` wide, whatever the image's aspect (:func:`contact_tile`).
    """
    height, width = prediction.size
    tile_w, tile_h, w, h, left, top = contact_tile(height, width, tile)
    grey = np.full((tile_h, tile_w, 3), 40, np.uint8)

    def fit(picture: np.ndarray) -> np.ndarray:
        resized = cv2.resize(picture, (w, h), interpolation=cv2.INTER_AREA)
        if (w, h) == (tile_w, tile_h):
            return resized
        boxed = grey.copy()
        boxed[top:top + h, left:left + w] = resized
        return boxed

    image = fit(prediction.rgb) if prediction.rgb is not None else grey.copy()
    if prediction.pose is not None:
        segment = horizon_segment(prediction.pose["pitch"], prediction.pose["roll"], prediction.pose["fov"],
                                  (height, width))
        if segment is not None:
            (x0, y0), (x1, y1) = segment
            sx, sy = w / width, h / height
            if (w, h) == (tile_w, tile_h):  # the picture fills its tile: one scale, as the tile was sized
                sx = sy = tile / height
            cv2.line(image, (left + round(x0 * sx), top + round(y0 * sy)),
                     (left + round(x1 * sx), top + round(y1 * sy)), (255, 220, 0), 2, cv2.LINE_AA)
    depth = grey
    if prediction.depth_m is not None:
        low, high = depth_range(prediction.depth_m, prediction.sky)
        depth = fit(depth_colours(prediction.depth_m, low, high, prediction.sky))
        label = f"{low:.0f}-{high:.0f} m" if low >= 10 else f"{low:.1f}-{high:.1f} m"
        cv2.rectangle(depth, (0, tile_h - 20), (min(tile_w, 8 * len(label) + 8), tile_h), (255, 255, 255), -1)
        _text(depth, label, (4, tile_h - 6))
    sky = (fit(np.repeat((np.clip(prediction.sky_prob, 0, 1) * 255).astype(np.uint8)[..., None], 3, axis=2))
           if prediction.sky_prob is not None else grey)
    text = np.full((tile_h, 2 * tile, 3), 255, np.uint8)
    lines = [prediction.name[:28]]
    if prediction.pose is not None:
        sources = prediction.pose_source or {}
        lines += [f"{k} {v:.1f} {'m' if k == 'height' else 'deg'}"
                  + (f" ({sources[k]})" if sources.get(k, "network") != "network" else "")
                  for k, v in prediction.pose.items()]
    for row, line in enumerate(lines):
        _text(text, line, (6, 22 + 24 * row))
    return [image, depth, sky, text]


def contact_row(prediction: Prediction, tile: int = CONTACT_TILE) -> np.ndarray:
    """:func:`contact_tiles` side by side: ``image | depth | sky | pose``, RGB."""
    return np.concatenate(contact_tiles(prediction, tile), axis=1)


def _pad(picture: np.ndarray, width: int) -> np.ndarray:
    """``picture`` centred in ``width`` columns of white."""
    extra = width - picture.shape[1]
    return np.pad(picture, ((0, 0), (extra // 2, extra - extra // 2), (0, 0)), constant_values=255)


def contact_sheet(rows: Sequence[np.ndarray | Sequence[np.ndarray]]) -> np.ndarray:
    """The sheet, RGB.

    Rows of :func:`contact_tiles` under column headings, each column as wide as its widest tile (tiles centred
    in it); rows given whole (:func:`contact_row`) are stacked, padded to the widest.
    """
    if all(isinstance(r, np.ndarray) for r in rows):
        whole = [np.asarray(r) for r in rows]
        width = max(r.shape[1] for r in whole)
        return np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=255)
                               for r in whole], axis=0)
    tiled = [list(r) for r in rows]
    widths = [max(r[k].shape[1] for r in tiled) for k in range(len(tiled[0]))]
    heading = np.full((CONTACT_HEADING, sum(widths), 3), 255, np.uint8)
    x = 0
    for title, width in zip(CONTACT_COLUMNS, widths):
        _text(heading, title, (x + 6, CONTACT_HEADING - 9))
        x += width
    lines = [np.concatenate([_pad(t, w) for t, w in zip(r, widths)], axis=1) for r in tiled]
    return np.concatenate([heading, *(np.pad(r, ((0, 4), (0, 0), (0, 0)), constant_values=255) for r in lines)],
                          axis=0)
