"""Named colours: the palette's colours and which of them a set of pixels shows.

Prompt-colour adherence asks whether an edit shows the colour its prompt names. Hue is what
white light leaves unchanged under shading, so chromatic pixels vote for the palette colour of
nearest hue (`pixel_hue_colors`); objects with too few saturated pixels are white or black by
their brighter pixels' value (`dominant_color`). The shipped model's training objects are
painted with the same palette (`default_model.appearance`).
"""

from __future__ import annotations

import colorsys

import numpy as np

# name -> (base albedo, accent albedo). Hues are >= 24 degrees apart; white light keeps them.
PALETTE: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "red": ((0.80, 0.10, 0.08), (0.36, 0.045, 0.036)),
    "orange": ((0.95, 0.50, 0.08), (0.43, 0.225, 0.036)),
    "yellow": ((0.92, 0.85, 0.12), (0.41, 0.38, 0.054)),
    "green": ((0.15, 0.65, 0.18), (0.068, 0.29, 0.081)),
    "blue": ((0.12, 0.25, 0.85), (0.054, 0.11, 0.38)),
    "purple": ((0.50, 0.15, 0.70), (0.225, 0.068, 0.315)),
    "white": ((0.92, 0.92, 0.90), (0.45, 0.45, 0.44)),
    "black": ((0.07, 0.07, 0.08), (0.22, 0.22, 0.23)),
}
COLORS = tuple(PALETTE)
ACHROMATIC_COLORS = ("white", "black")
# The palette colours with a hue, and their base colours' hues in [0, 1) (`pixel_hue_colors`).
CHROMATIC_COLORS = tuple(name for name in COLORS if name not in ACHROMATIC_COLORS)
CHROMATIC_HUES = np.asarray([colorsys.rgb_to_hsv(*PALETTE[name][0])[0]
                             for name in CHROMATIC_COLORS])

# `dominant_color`: a pixel is chromatic above this saturation (and this value); an object is
# chromatic when most of its pixels are. An achromatic object is white when its brighter pixels
# (the WHITE_PERCENTILE) exceed WHITE_MIN_VALUE: black and its accent stay below it under full
# light, white's base colour stays above it even under ambient light alone (>= 0.3).
CHROMATIC_SATURATION = 0.35
CHROMATIC_MIN_VALUE = 0.06
WHITE_PERCENTILE = 75
WHITE_MIN_VALUE = 0.25


def pixel_hue_colors(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Each pixel's nearest chromatic palette colour by hue (hue is unchanged by white light).

  Args:
    rgb: [..., 3] colours in [0, 1].
  Returns:
    chromatic: [...] bool, saturated and bright enough for its hue to mean something;
    nearest: [...] index into `CHROMATIC_COLORS` of the palette hue nearest to the pixel's.
  """
  rgb = np.asarray(rgb, np.float64)
  value = rgb.max(-1)
  chroma = value - rgb.min(-1)
  chromatic = (chroma / np.maximum(value, 1e-6) > CHROMATIC_SATURATION) & (
      value > CHROMATIC_MIN_VALUE)
  red, green, blue = np.moveaxis(rgb, -1, 0)
  safe_chroma = np.maximum(chroma, 1e-12)
  # Hue in [0, 1) as colorsys defines it, vectorised.
  hue = np.where(value == red, (green - blue) / safe_chroma,
                 np.where(value == green, 2.0 + (blue - red) / safe_chroma,
                          4.0 + (red - green) / safe_chroma))
  hue = np.mod(hue / 6.0, 1.0)
  gap = np.abs(hue[..., None] - CHROMATIC_HUES)
  return chromatic, np.argmin(np.minimum(gap, 1.0 - gap), -1)


def dominant_color(rgb: np.ndarray) -> str:
  """The PALETTE colour an object's pixels show most, robust to shading.

  Args:
    rgb: [P, 3] the object's pixel colours in [0, 1] (P >= 1).
  Returns:
    For mostly saturated pixels, the chromatic palette colour whose hue is nearest to most of
    them (`pixel_hue_colors`); otherwise "white" or "black" by the value of the brighter pixels.
  """
  rgb = np.asarray(rgb, np.float64).reshape(-1, 3)
  chromatic, nearest = pixel_hue_colors(rgb)
  if chromatic.mean() < 0.5:
    value = rgb.max(-1)
    return "white" if np.percentile(value, WHITE_PERCENTILE) > WHITE_MIN_VALUE else "black"
  votes = np.bincount(nearest[chromatic], minlength=len(CHROMATIC_COLORS))
  return CHROMATIC_COLORS[int(np.argmax(votes))]


def named_color(words: list[str]) -> str | None:
  """The first palette colour among a prompt's words (None when it names none)."""
  return next((word for word in words if word in PALETTE), None)
