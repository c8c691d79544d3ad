"""Exact first-hit ray casting (numpy) against unit primitives and triangle meshes.

Used to render synthetic scenes with ground truth, so it favours exactness and simplicity; speed
comes from vectorising over rays and, for meshes, a one-level hierarchy of triangle clusters.

Each shape lives in its own canonical frame:
  sphere    radius 1 around the origin;
  box       [-1, 1]^3;
  cylinder  radius 1 around the z axis, z in [-1, 1], with both caps;
  mesh      any triangles (`TriangleClusters`).
Rays are given in that frame with *unnormalised* directions: mapping a world ray (origin o, unit
direction d) through the inverse of an affine object transform keeps the hit parameter t equal
to the world distance. Every intersector returns
  t: [R] float64 distance of the first hit with t > MIN_DISTANCE (inf where the ray misses);
  normals: [R, 3] canonical-frame normals at the hits (not unit length; zero on misses).
"""

from __future__ import annotations

import dataclasses

import numpy as np

# Hits closer than this are ignored: rays start at a camera, never on a surface.
MIN_DISTANCE = 1e-6


def linear_map(matrix: np.ndarray, vectors: np.ndarray) -> np.ndarray:
  """[3, 3] `matrix` applied to [..., 3] `vectors`.

  Written out per column: numpy's matmul takes ~10x longer for this tall, thin shape.
  """
  return (vectors[..., 0:1] * matrix[:, 0] + vectors[..., 1:2] * matrix[:, 1]
          + vectors[..., 2:3] * matrix[:, 2])


def _first_positive(candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """The smallest candidate above MIN_DISTANCE per ray ([R, K] -> t [R], index [R])."""
  candidates = np.where(candidates > MIN_DISTANCE, candidates, np.inf)
  index = np.argmin(candidates, axis=-1)
  return np.take_along_axis(candidates, index[:, None], -1)[:, 0], index


def intersect_sphere(origins: np.ndarray, directions: np.ndarray):
  """Rays [R, 3] against the unit sphere: (t [R], normals [R, 3])."""
  a = np.sum(directions**2, -1)
  half_b = np.sum(origins * directions, -1)
  c = np.sum(origins**2, -1) - 1.0
  discriminant = half_b**2 - a * c
  root = np.sqrt(np.maximum(discriminant, 0.0))
  roots = np.stack([-half_b - root, -half_b + root], -1) / a[:, None]
  t, _ = _first_positive(np.where(discriminant[:, None] >= 0, roots, np.inf))
  hit = np.isfinite(t)
  normals = np.where(hit[:, None], origins + np.where(hit, t, 0.0)[:, None] * directions, 0.0)
  return t, normals


def slab_interval(origins, directions, lower, upper):
  """Entry and exit distances of rays through axis-aligned boxes (broadcasting over leading axes).

  Args:
    origins, directions: [..., 3] rays.
    lower, upper: [..., 3] box corners.
  Returns:
    (entry, exit), each [...]; the ray meets the box iff exit >= max(entry, 0).
  """
  entry, exit_ = -np.inf, np.inf
  # Per axis rather than reducing over a trailing axis of 3: several times faster in numpy.
  with np.errstate(divide="ignore", invalid="ignore"):
    for axis in range(3):
      origin, direction = origins[..., axis], directions[..., axis]
      to_lower = (lower[..., axis] - origin) / direction
      to_upper = (upper[..., axis] - origin) / direction
      near, far = np.minimum(to_lower, to_upper), np.maximum(to_lower, to_upper)
      # A ray parallel to the slab is inside it for all t (faces included) or never.
      parallel = direction == 0
      if np.any(parallel):
        inside = (lower[..., axis] <= origin) & (origin <= upper[..., axis])
        near = np.where(parallel, np.where(inside, -np.inf, np.inf), near)
        far = np.where(parallel, np.where(inside, np.inf, -np.inf), far)
      entry, exit_ = np.maximum(entry, near), np.minimum(exit_, far)
  return entry, exit_


def intersect_box(origins: np.ndarray, directions: np.ndarray):
  """Rays [R, 3] against the cube [-1, 1]^3: (t [R], normals [R, 3])."""
  entry, exit_ = slab_interval(origins, directions, np.full(3, -1.0), np.full(3, 1.0))
  t, _ = _first_positive(np.where((exit_ >= entry)[:, None], np.stack([entry, exit_], -1),
                                  np.inf))
  hit = np.isfinite(t)
  points = origins + np.where(hit, t, 0.0)[:, None] * directions
  # The face hit is the axis where the point is farthest from the centre.
  axis = np.argmax(np.abs(points), -1)
  normals = np.zeros_like(points)
  rows = np.arange(len(points))
  normals[rows, axis] = np.sign(points[rows, axis])
  return t, np.where(hit[:, None], normals, 0.0)


def intersect_cylinder(origins: np.ndarray, directions: np.ndarray):
  """Rays [R, 3] against the capped unit cylinder: (t [R], normals [R, 3])."""
  xy_origins, xy_directions = origins[:, :2], directions[:, :2]
  a = np.sum(xy_directions**2, -1)
  half_b = np.sum(xy_origins * xy_directions, -1)
  c = np.sum(xy_origins**2, -1) - 1.0
  discriminant = half_b**2 - a * c
  root = np.sqrt(np.maximum(discriminant, 0.0))
  with np.errstate(divide="ignore", invalid="ignore"):
    side = np.stack([-half_b - root, -half_b + root], -1) / a[:, None]
    caps = (np.array([-1.0, 1.0]) - origins[:, 2:3]) / directions[:, 2:3]
  side_height = origins[:, 2:3] + side * directions[:, 2:3]
  side = np.where((discriminant[:, None] >= 0) & (np.abs(side_height) <= 1), side, np.inf)
  cap_points = origins[:, None, :2] + caps[..., None] * directions[:, None, :2]
  caps = np.where(np.sum(cap_points**2, -1) <= 1, caps, np.inf)
  candidates = np.concatenate([side, caps], -1)
  t, which = _first_positive(np.where(np.isnan(candidates), np.inf, candidates))
  hit = np.isfinite(t)
  points = origins + np.where(hit, t, 0.0)[:, None] * directions
  side_normals = points * np.array([1.0, 1.0, 0.0])
  cap_normals = np.zeros_like(points)
  cap_normals[:, 2] = np.where(which == 2, -1.0, 1.0)
  normals = np.where((which < 2)[:, None], side_normals, cap_normals)
  return t, np.where(hit[:, None], normals, 0.0)


@dataclasses.dataclass(frozen=True)
class TriangleClusters:
  """A triangle mesh grouped into spatially compact clusters of equal size, with their boxes.

  Rays are tested against the cluster boxes first and then only against the triangles of the
  clusters they enter: a one-level bounding volume hierarchy that vectorises well in numpy.

  Attributes:
    corners: [K, C, 3, 3] triangle vertices (cluster, triangle, corner, xyz).
    corner_normals: [K, C, 3, 3] vertex normals at those corners (for smooth shading).
    lower, upper: [K, 3] cluster bounding boxes.
    vertex0, edge1, edge2: [3, K, C] the first corner and the two edges from it, coordinate
      first, as the ray-triangle test consumes them.
  """

  corners: np.ndarray
  corner_normals: np.ndarray
  lower: np.ndarray
  upper: np.ndarray
  vertex0: np.ndarray
  edge1: np.ndarray
  edge2: np.ndarray

  @classmethod
  def build(cls, vertices, faces, vertex_normals, cluster_size: int = 32) -> "TriangleClusters":
    """Clusters `faces` ([T, 3] ints into `vertices` [V, 3], normals [V, 3]) spatially.

    Clusters come from recursive median splits along the longest axis of the triangle
    centroids; the last cluster is padded by repeating a triangle (which cannot change a hit).
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    centroids = vertices[faces].mean(1)
    order = _spatial_order(centroids, np.arange(len(faces)), cluster_size)
    padding = -len(order) % cluster_size
    order = np.concatenate([order, np.repeat(order[-1:], padding)]).reshape(-1, cluster_size)
    corners = vertices[faces[order]]
    coordinate_first = lambda array: np.ascontiguousarray(np.moveaxis(array, -1, 0))
    return cls(corners=corners,
               corner_normals=np.asarray(vertex_normals, np.float64)[faces[order]],
               lower=corners.min(axis=(1, 2)), upper=corners.max(axis=(1, 2)),
               vertex0=coordinate_first(corners[:, :, 0]),
               edge1=coordinate_first(corners[:, :, 1] - corners[:, :, 0]),
               edge2=coordinate_first(corners[:, :, 2] - corners[:, :, 0]))


def _spatial_order(centroids: np.ndarray, indices: np.ndarray, leaf_size: int) -> np.ndarray:
  """Triangle indices ordered so that consecutive runs of `leaf_size` are spatially compact."""
  if len(indices) <= leaf_size:
    return indices
  points = centroids[indices]
  axis = np.argmax(np.ptp(points, axis=0))
  indices = indices[np.argsort(points[:, axis], kind="stable")]
  # Split at a multiple of the leaf size so that only the very last cluster is partial.
  split = leaf_size * -(-len(indices) // (2 * leaf_size))
  return np.concatenate([_spatial_order(centroids, indices[:split], leaf_size),
                         _spatial_order(centroids, indices[split:], leaf_size)])


def _cross(a, b):
  """Cross product of vectors given as 3 coordinate arrays each."""
  return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def intersect_mesh(clusters: TriangleClusters, origins: np.ndarray, directions: np.ndarray,
                   rays_per_chunk: int = 1024):
  """Rays [R, 3] against a clustered mesh (Moller-Trumbore): (t [R], normals [R, 3]).

  Normals interpolate the vertex normals barycentrically.
  """
  count = len(origins)
  t = np.full(count, np.inf)
  normals = np.zeros((count, 3))
  entry, exit_ = slab_interval(origins, directions, clusters.lower.min(0), clusters.upper.max(0))
  candidates = np.nonzero(exit_ >= np.maximum(entry, 0.0))[0]
  for start in range(0, len(candidates), rays_per_chunk):
    rays = candidates[start:start + rays_per_chunk]
    entry, exit_ = slab_interval(origins[rays, None], directions[rays, None], clusters.lower,
                                 clusters.upper)
    ray, cluster = np.nonzero(exit_ >= np.maximum(entry, 0.0))  # (ray, cluster) pairs
    if not len(ray):
      continue
    # Every quantity below is a tuple of 3 coordinate arrays of shape [P, C] (or [P, 1]).
    origin = tuple(origins[rays[ray], axis, None] for axis in range(3))
    direction = tuple(directions[rays[ray], axis, None] for axis in range(3))
    vertex0, edge1, edge2 = ((array[0, cluster], array[1, cluster], array[2, cluster])
                             for array in (clusters.vertex0, clusters.edge1, clusters.edge2))
    p = _cross(direction, edge2)
    determinant = _dot(edge1, p)
    offset = tuple(o - v for o, v in zip(origin, vertex0))
    q = _cross(offset, edge1)
    with np.errstate(divide="ignore", invalid="ignore"):
      inverse = 1.0 / determinant
      u = _dot(offset, p) * inverse
      v = _dot(direction, q) * inverse
      distance = _dot(edge2, q) * inverse
    inside = (np.abs(determinant) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1)
    distance = np.where(inside & (distance > MIN_DISTANCE), distance, np.inf)
    best = np.argmin(distance, -1)  # per pair
    pair_t = np.take_along_axis(distance, best[:, None], -1)[:, 0]
    # The nearest pair per ray: sort pairs by (ray, t) and keep each ray's first.
    order = np.lexsort((pair_t, ray))
    winners = order[np.unique(ray[order], return_index=True)[1]]
    winners = winners[np.isfinite(pair_t[winners])]
    if not len(winners):
      continue
    triangle = best[winners]
    barycentric = np.stack([1 - u[winners, triangle] - v[winners, triangle],
                            u[winners, triangle], v[winners, triangle]], -1)
    corner_normals = clusters.corner_normals[cluster[winners], triangle]  # [W, 3, 3]
    t[rays[ray[winners]]] = pair_t[winners]
    normals[rays[ray[winners]]] = np.einsum("wc,wci->wi", barycentric, corner_normals)
  return t, normals
