"""Thin Flax fields: grid encoding -> small MLPs -> density (and colour).

All positions are in the unit cube [0, 1]^3 (the caller maps scene or contracted coordinates
there); directions are unit world-space vectors.
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from signerf_jax.math import with_derivative
from signerf_jax.nerf.encoding import GridLayout, HashGridEncoding, spherical_harmonics

# exp's gradient is clamped at this input (instant-NGP's "trunc_exp"): one huge activation must not
# blow up the update of the whole table.
_EXP_GRADIENT_CLAMP = 15.0
# Forward values stay below float32 max (the compositing clamps optical depth anyway).
_EXP_VALUE_CLAMP = 80.0
# The radiance field's fixed sizes (no capacity rule or config sets them): features the density
# MLP passes to the colour MLP (with the density, instant-NGP's 16 outputs), the colour MLP's
# hidden layers, and the size of a per-image appearance code.
GEOMETRY_FEATURES = 15
COLOR_HIDDEN_LAYERS = 2
APPEARANCE_FEATURES = 8


@with_derivative(lambda x: jnp.exp(jnp.minimum(x, _EXP_GRADIENT_CLAMP)))
def truncated_exp(x):
  """exp(x) (capped at exp(80)) with its derivative evaluated at min(x, 15)."""
  return jnp.exp(jnp.minimum(x, _EXP_VALUE_CLAMP))


class MLP(nn.Module):
  """ReLU layers of `width` then a linear output layer."""

  width: int
  num_hidden_layers: int
  output_dim: int

  @nn.compact
  def __call__(self, x):
    for _ in range(self.num_hidden_layers):
      x = nn.relu(nn.Dense(self.width)(x))
    return nn.Dense(self.output_dim)(x)


class DensityField(nn.Module):
  """Density only (proposal networks): grid -> tiny MLP -> exp.

  Attributes:
    layout: the grid.
    width: hidden width.
    initial_density: density of the untrained field (see `RadianceField`).
  """

  layout: GridLayout
  width: int = 16
  initial_density: float = 1.0

  @nn.compact
  def __call__(self, points):
    """points: [..., 3] unit cube -> [...] densities >= 0."""
    raw = MLP(self.width, 1, 1)(HashGridEncoding(self.layout)(points))
    return truncated_exp(raw[..., 0] + jnp.log(self.initial_density))


class RadianceField(nn.Module):
  """Density from position; colour from a geometry feature, view direction and (optionally) a
  per-image appearance embedding (NeRF-W style, for real captures with varying exposure).

  Attributes:
    layout: the position encoding's grid.
    width: hidden width of both MLPs.
    sh_degree: spherical-harmonics degree of the direction encoding (degree**2 channels).
    num_appearance_embeddings: number of training images with an embedding (0 = off).
    initial_density: density of the untrained field (its raw output is ~0), in 1 / scene units.
      Too thick and the scene starts as fog the colour MLP paints in the background colour; too
      thin and surfaces need hundreds of steps to become opaque (soft surfaces, wrong depth).
  """

  layout: GridLayout
  width: int = 64
  sh_degree: int = 4
  num_appearance_embeddings: int = 0
  initial_density: float = 1.0

  def setup(self):
    self.encoding = HashGridEncoding(self.layout)
    self.density_mlp = MLP(self.width, 1, 1 + GEOMETRY_FEATURES)
    self.color_mlp = MLP(self.width, COLOR_HIDDEN_LAYERS, 3)
    if self.num_appearance_embeddings:
      self.appearance = nn.Embed(self.num_appearance_embeddings, APPEARANCE_FEATURES,
                                 embedding_init=nn.initializers.zeros)

  def _geometry(self, points, level_weights):
    raw = self.density_mlp(self.encoding(points, level_weights))
    return truncated_exp(raw[..., 0] + jnp.log(self.initial_density)), raw[..., 1:]

  def density(self, points, level_weights=None):
    """points: [..., 3] unit cube -> [...] densities."""
    return self._geometry(points, level_weights)[0]

  def geometry(self, points, level_weights=None):
    """points: [..., 3] unit cube -> density [...] and the geometry features the colour takes
    [..., GEOMETRY_FEATURES] (rendering evaluates the colour only where it is seen: `colour`)."""
    return self._geometry(points, level_weights)

  def __call__(self, points, directions, appearance_indices=None, level_weights=None):
    """Density and colour.

    Args:
      points: [..., 3] unit cube.
      directions: [..., 3] unit vectors.
      appearance_indices: None or [...] int32 image index; negative = a novel view (the mean code).
      level_weights: None or [L] coarse-to-fine weights of the grid's levels.
    Returns:
      density [...] >= 0 and rgb [..., 3] in [0, 1].
    """
    density, geometry = self._geometry(points, level_weights)
    return density, self.colour(geometry, directions, appearance_indices)

  def colour(self, geometry, directions, appearance_indices=None):
    """rgb [..., 3] in [0, 1] from geometry features [..., GEOMETRY_FEATURES] (`geometry`), unit
    directions [..., 3] and appearance indices (None or [...], as `__call__`)."""
    inputs: Sequence[jax.Array] = [geometry, spherical_harmonics(directions, self.sh_degree)]
    if self.num_appearance_embeddings:
      indices = jnp.zeros(geometry.shape[:-1], jnp.int32) if appearance_indices is None else (
          appearance_indices)
      embedding = self.appearance(jnp.clip(indices, 0, self.num_appearance_embeddings - 1))
      # A novel view has no code of its own: it gets the training views' average appearance
      # (nerfacto's choice), not the zero code, which training never anchors.
      average = jnp.mean(self.appearance.embedding, axis=0)
      inputs.append(jnp.where((indices >= 0)[..., None], embedding, average))
    return nn.sigmoid(self.color_mlp(jnp.concatenate(inputs, axis=-1)))
