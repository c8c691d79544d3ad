"""Object appearances: a palette colour and a pattern defined on the object's own 3D coordinates.

An appearance is a base colour from `PALETTE` and a pattern from `PATTERNS` that paints some of
the surface in the colour's accent (the same hue, darker; grey for black). The pattern is a
function of *object coordinates*: the object's frame (its base centre, its yaw) scaled so that
its footprint radius is 1. A surface point therefore has one albedo whatever camera sees it,
which is what makes the tiles of a multi-view sheet agree.

Patterns, in object units (footprint radius = 1), before the appearance's random scale:
  plain      no accent;
  striped    parallel bands of period STRIPE_PERIOD, STRIPE_ACCENT_FRACTION of each in accent,
             across the pattern frame's z axis (horizontal bands, vertical bands or diagonal);
  checkered  a 3D checkerboard of cubes with side CHECKER_SIZE (half the surface in accent);
  spotted    balls of radius SPOT_RADIUS on a cubic lattice of spacing SPOT_SPACING: round dots
             of varying size where the surface cuts them (about a fifth of the surface).
Edges are a linear ramp EDGE_WIDTH wide so that 64-pixel renders do not alias badly.

The accent covers at most half of the surface and keeps the base hue, so the base colour stays
the dominant colour of the object: `metrics.colors.dominant_color` (prompt adherence) recovers it
from shaded renders. Shading itself (Lambert plus ambient under a white light, which keeps hue)
is the synthetic renderer's (`signerf_jax.data.synthetic_render.render`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from signerf_jax.errors import InputError
from signerf_jax.metrics.colors import COLORS, PALETTE

PATTERNS = ("plain", "striped", "checkered", "spotted")

STRIPE_PERIOD = 0.55
STRIPE_ACCENT_FRACTION = 0.4
CHECKER_SIZE = 0.45
SPOT_SPACING = 0.6
SPOT_RADIUS = 0.22
EDGE_WIDTH = 0.06
PATTERN_SCALE_RANGE = (0.8, 1.25)
# Stripe directions: tilt of the bands' normal from vertical (0: horizontal bands), and odds.
STRIPE_TILTS_DEGREES = (0.0, 90.0, 45.0)
STRIPE_TILT_PROBABILITIES = (0.5, 0.3, 0.2)



@dataclasses.dataclass(frozen=True)
class Appearance:
  """A colour, a pattern and where the pattern sits on the object.

  Attributes:
    color: a PALETTE name.
    pattern: one of PATTERNS.
    rotation: [3, 3] pattern frame: object coordinates x map to pattern coordinates
      (x - offset) @ rotation.
    offset: [3] pattern origin in object coordinates.
    scale: multiplies every pattern length.
  """

  color: str
  pattern: str
  rotation: np.ndarray
  offset: np.ndarray
  scale: float

  def __post_init__(self):
    if self.color not in PALETTE or self.pattern not in PATTERNS:
      raise InputError(f"colour must be one of {COLORS} and pattern one of {PATTERNS}, got "
                       f"{self.color!r}, {self.pattern!r}", field="appearance")

  def accent_weight(self, points: np.ndarray) -> np.ndarray:
    """[R] in [0, 1]: how much accent colour object-coordinate `points` [R, 3] get."""
    if self.pattern == "plain":
      return np.zeros(len(points))
    local = (np.asarray(points, np.float64) - self.offset) @ self.rotation / self.scale
    if self.pattern == "striped":
      phase = np.mod(local[:, 2] / STRIPE_PERIOD, 1.0)
      # Positive inside a band: half the band width minus the distance to its centre line.
      signed = (STRIPE_ACCENT_FRACTION / 2 - np.abs(phase - 0.5)) * STRIPE_PERIOD
    elif self.pattern == "checkered":
      cells = np.floor(local / CHECKER_SIZE)
      to_boundary = np.abs(local - (cells + 0.5) * CHECKER_SIZE)
      distance = CHECKER_SIZE / 2 - to_boundary.max(-1)
      signed = np.where(np.mod(cells.sum(-1), 2) == 1, distance, -distance)
    else:  # spotted
      nearest = np.round(local / SPOT_SPACING) * SPOT_SPACING
      signed = SPOT_RADIUS - np.linalg.norm(local - nearest, axis=-1)
    return np.clip(0.5 + signed * self.scale / EDGE_WIDTH, 0.0, 1.0)

  def albedo(self, points: np.ndarray) -> np.ndarray:
    """[R, 3] albedo at object-coordinate `points` [R, 3]."""
    base, accent = (np.asarray(color) for color in PALETTE[self.color])
    return base + self.accent_weight(points)[:, None] * (accent - base)


def random_appearance(rng: np.random.Generator, color: str, pattern: str) -> Appearance:
  """The `color` and `pattern` with a random pattern placement (yaw, offset, scale, tilt)."""
  tilt = 0.0
  if pattern == "striped":
    tilt = STRIPE_TILTS_DEGREES[rng.choice(len(STRIPE_TILTS_DEGREES),
                                           p=STRIPE_TILT_PROBABILITIES)]
  rotation = (trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), (0.0, 0.0, 1.0))
              @ trimesh.transformations.rotation_matrix(np.radians(tilt), (1.0, 0.0, 0.0)))[:3, :3]
  return Appearance(color=color, pattern=pattern, rotation=rotation,
                    offset=rng.uniform(-1.0, 1.0, 3), scale=float(rng.uniform(*PATTERN_SCALE_RANGE)))
