"""Figures for people: labelled image grids (sheet previews, before/after renders)."""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

# Figures are enlarged (nearest neighbour) until a cell is at least this tall, so that 64-pixel
# tiles and their labels stay legible.
MIN_CELL_HEIGHT = 192
LABEL_HEIGHT = 22
GAP = 4


def as_rgb(image: np.ndarray) -> np.ndarray:
  """[H, W], [H, W, 1] or [H, W, 3] in [0, 1] -> [H, W, 3] float32."""
  image = np.asarray(image, np.float32)
  if image.ndim == 3 and image.shape[-1] == 1:
    image = image[..., 0]
  return np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image


def outline(image: np.ndarray, mask: np.ndarray, color=(1.0, 0.1, 0.1)) -> np.ndarray:
  """[H, W, 3] float32: `image` ([H, W] or [H, W, 3] in [0, 1]) with the boundary pixels of
  `mask` ([H, W] bool: its pixels with a neighbour outside it) drawn in `color`."""
  image = as_rgb(image).copy()
  inside = np.pad(np.asarray(mask, bool), 1)
  interior = inside[:-2, 1:-1] & inside[2:, 1:-1] & inside[1:-1, :-2] & inside[1:-1, 2:]
  image[inside[1:-1, 1:-1] & ~interior] = color
  return image


def image_grid(rows: Sequence[Sequence[np.ndarray]], labels: Sequence[Sequence[str]] | None = None
               ) -> np.ndarray:
  """Images laid out in rows (each cell resized to the first image's size, enlarged together),
  white gaps, an optional label above each cell. Returns [H, W, 3] float32 in [0, 1]."""
  cell_height, cell_width = np.shape(rows[0][0])[:2]
  scale = max(1, -(-MIN_CELL_HEIGHT // cell_height))
  cell_height, cell_width = cell_height * scale, cell_width * scale
  label_height = LABEL_HEIGHT if labels is not None else 0
  columns = max(len(row) for row in rows)
  height = len(rows) * (cell_height + label_height + GAP) + GAP
  width = columns * (cell_width + GAP) + GAP
  canvas = np.full((height, width, 3), 255, np.uint8)  # OpenCV draws text on 8 bits only.
  for row_index, row in enumerate(rows):
    for column_index, image in enumerate(row):
      top = GAP + row_index * (cell_height + label_height + GAP) + label_height
      left = GAP + column_index * (cell_width + GAP)
      cell = cv2.resize(as_rgb(image), (cell_width, cell_height), interpolation=cv2.INTER_NEAREST)
      canvas[top:top + cell_height, left:left + cell_width] = np.round(
          np.clip(cell, 0, 1) * 255).astype(np.uint8)
      if labels is not None and labels[row_index][column_index]:
        cv2.putText(canvas, labels[row_index][column_index], (left + 2, top - 6),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
  return canvas.astype(np.float32) / 255
