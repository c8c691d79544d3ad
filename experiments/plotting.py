"""Line and interval charts for the experiments' PNG plots, drawn with OpenCV (the project's
image library).

    panel = line_chart("NeRF training", [Series("measured", [1, 2, 4], [3.1, 5.9, 11.0])],
                       x_label="devices", y_label="rays / s")
    write_panels(path, [panel, ...])
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from signerf_jax import files

# BGR, matplotlib's ten default colours (tab10).
COLOURS = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
           (75, 86, 140), (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23))
FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK, GRID = (0, 0, 0), (220, 220, 220)


@dataclasses.dataclass(frozen=True)
class Series:
  """One line: points (x, y) in data units, drawn dashed (thin, no markers) if `dashed`."""

  label: str
  x: Sequence[float]
  y: Sequence[float]
  dashed: bool = False


def _text(canvas, text: str, origin, colour=BLACK, scale: float = 0.45) -> None:
  cv2.putText(canvas, text, (int(origin[0]), int(origin[1])), FONT, scale, colour, 1, cv2.LINE_AA)


def _ticks(low: float, high: float, count: int = 5) -> np.ndarray:
  """About `count` round tick values covering [low, high] (a single value gets ticks around it)."""
  if high <= low:
    low, high = low - max(abs(low), 1.0) / 2, high + max(abs(high), 1.0) / 2
  step = (high - low) / count
  magnitude = 10.0**np.floor(np.log10(step))
  step = min((factor * magnitude for factor in (1, 2, 5, 10) if factor * magnitude >= step))
  # Whole multiples of the step: adding the step up from `low` makes 0 into 1.4e-17.
  return np.arange(np.floor(low / step), high / step + 0.5) * step


def line_chart(title: str, series: Sequence[Series], x_label: str, y_label: str,
               x_ticks: Sequence[float] | None = None, width: int = 460, height: int = 340,
               y_from_zero: bool = True) -> np.ndarray:
  """A chart of `series` with grid lines and a legend; [height, width, 3] uint8 BGR.

  Args:
    x_ticks: where the vertical grid lines and x labels go (default: round values).
    y_from_zero: the y axis starts at 0 (else at the lowest value).
  """
  canvas = np.full((height, width, 3), 255, np.uint8)
  left, right, top, bottom = 60, width - 15, 45, height - 45
  xs = np.concatenate([np.asarray(line.x, float) for line in series])
  ys = np.concatenate([np.asarray(line.y, float) for line in series])
  x_ticks = _ticks(xs.min(), xs.max()) if x_ticks is None else np.asarray(x_ticks, float)
  y_ticks = _ticks(0.0 if y_from_zero else ys.min(), ys.max())
  x_low, x_high = min(x_ticks[0], xs.min()), max(x_ticks[-1], xs.max())
  y_low, y_high = y_ticks[0], max(y_ticks[-1], ys.max())
  to_pixel = lambda x, y: (int(round(left + (right - left) * (x - x_low) / max(x_high - x_low,
                                                                               1e-12))),
                           int(round(bottom - (bottom - top) * (y - y_low) / max(y_high - y_low,
                                                                                 1e-12))))
  for value in y_ticks:
    y = to_pixel(x_low, value)[1]
    cv2.line(canvas, (left, y), (right, y), GRID, 1)
    _text(canvas, f"{value:g}", (5, y + 4))
  for value in x_ticks:
    x = to_pixel(value, y_low)[0]
    cv2.line(canvas, (x, top), (x, bottom), GRID, 1)
    _text(canvas, f"{value:g}", (x - 6, bottom + 16))
  _text(canvas, title, (10, 18), scale=0.55)
  _text(canvas, x_label, ((left + right) // 2 - 4 * len(x_label), height - 8))
  _text(canvas, y_label, (5, top - 12))
  for index, line in enumerate(series):
    colour = COLOURS[index % len(COLOURS)]
    pixels = [to_pixel(x, y) for x, y in zip(line.x, line.y)]
    for start, end in zip(pixels[:-1], pixels[1:]):
      if line.dashed:
        for fraction in np.arange(0, 1, 0.1):
          a = np.add(start, np.subtract(end, start) * fraction).astype(int)
          b = np.add(start, np.subtract(end, start) * (fraction + 0.05)).astype(int)
          cv2.line(canvas, tuple(map(int, a)), tuple(map(int, b)), colour, 1, cv2.LINE_AA)
      else:
        cv2.line(canvas, start, end, colour, 2, cv2.LINE_AA)
    if not line.dashed:
      for pixel in pixels:
        cv2.circle(canvas, pixel, 4, colour, -1, cv2.LINE_AA)
    _text(canvas, line.label, (left + 10, top + 16 + 18 * index), colour)
  return canvas


def interval_chart(title: str, rows: Sequence[tuple[str, float, float, float]], x_label: str,
                   width: int = 460, height: int = 200) -> np.ndarray:
  """One horizontal interval per row (label, mean, low, high): a line from low to high with a
  dot at the mean; [height, width, 3] uint8 BGR. Rows with a None value are listed, not drawn."""
  canvas = np.full((height, width, 3), 255, np.uint8)
  left, right, top, bottom = 110, width - 15, 40, height - 40
  known = [row for row in rows if None not in row[1:]]
  values = np.asarray([row[1:] for row in known], float).reshape(-1, 3)
  ticks = _ticks(values.min(), values.max()) if len(values) else np.array([0.0, 1.0])
  low, high = min(ticks[0], values.min(initial=ticks[0])), max(ticks[-1],
                                                                values.max(initial=ticks[-1]))
  to_x = lambda value: int(round(left + (right - left) * (value - low) / max(high - low, 1e-12)))
  for value in ticks:
    cv2.line(canvas, (to_x(value), top), (to_x(value), bottom), GRID, 1)
    _text(canvas, f"{value:g}", (to_x(value) - 6, bottom + 16))
  _text(canvas, title, (10, 18), scale=0.55)
  _text(canvas, x_label, ((left + right) // 2 - 4 * len(x_label), height - 8))
  step = (bottom - top) / max(len(rows), 1)
  for index, (label, mean, interval_low, interval_high) in enumerate(rows):
    y = int(round(top + step * (index + 0.5)))
    colour = COLOURS[index % len(COLOURS)]
    _text(canvas, label, (5, y + 4), colour)
    if None in (mean, interval_low, interval_high):
      _text(canvas, "not measured", (left + 5, y + 4), colour)
      continue
    cv2.line(canvas, (to_x(interval_low), y), (to_x(interval_high), y), colour, 2, cv2.LINE_AA)
    cv2.circle(canvas, (to_x(mean), y), 4, colour, -1, cv2.LINE_AA)
  return canvas


def side_by_side(panels: Sequence[np.ndarray]) -> np.ndarray:
  """Charts (same height, uint8 BGR) side by side: [H, W, 3] float32 RGB in [0, 1]."""
  return np.concatenate(panels, axis=1)[..., ::-1].astype(np.float32) / 255


def stacked(rows: Sequence[np.ndarray], gap: int = 8) -> np.ndarray:
  """[H, W, 3] float32 RGB images one below the other, left-aligned on white, `gap` px apart."""
  width = max(row.shape[1] for row in rows)
  return np.concatenate([np.pad(row, ((0, gap), (0, width - row.shape[1]), (0, 0)),
                                constant_values=1.0) for row in rows])


def write_panels(path: str | Path, panels: Sequence[np.ndarray]) -> None:
  """Writes charts side by side (same height) as one PNG, atomically."""
  files.write_image(path, side_by_side(panels))
