"""Exact per-pixel depth of a triangle mesh for any `Cameras`, in JAX.

Tile-binned ray casting with a scatter-min z-buffer (the binning GPU rasterisers use), done in
each camera's frame, where every ray starts at the origin:
  1. Every pixel-centre ray is given by its undistorted normalised image coordinates (x, y), the
     same rays `camera.pixel_rays` shoots (lens distortion is honoured; a fisheye's rays 90
     degrees or more off its axis, which have no z-depth, hit nothing). The image is cut into
     `tile_size`-pixel square tiles; each column of tiles gets the range of its rays' x, each row
     the range of y (widened to be monotone along the grid, so a rectangle of the image plane
     maps to a contiguous block of tiles).
  2. Every triangle is projected (pinhole: a ray hits a triangle only if its (x, y) lies in the
     triangle's projection) to its bounding rectangle, which selects a block of tiles. A
     triangle reaching behind the camera has an unbounded projection and takes every tile; one
     entirely behind the camera cannot be hit by a forward ray and takes none.
  3. The (triangle, tile) pairs are enumerated into a list of static length `capacity` (prefix sum
     of the per-triangle tile counts plus a search). Binning is conservative, so the result is
     exact unless the list overflows, which `overflow` reports; `render_mesh_depth` sizes the list.
  4. Every pair intersects the tile's pixel rays with its triangle (Moller-Trumbore, factored as
     below) and the nearest hit per pixel wins through a scatter-min.

Work is proportional to the pixels each triangle's bounding box covers, not pixels x triangles.
Because the rays are the cameras' own rays, the depth of a distorted camera is the depth along its
distorted rays: the mesh lines up pixel for pixel with a NeRF rendered with the same cameras.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax import camera as camera_lib
from signerf_jax import lens
from signerf_jax.geometry import mesh as mesh_lib

# A ray hits a triangle when its barycentric coordinates are >= -tolerance (relative to the
# triangle). Float32 rounding can otherwise leave a ray that runs along a shared edge missing
# both triangles, a pinhole in the depth map; the tolerance only adds hits where the neighbouring
# triangle's plane gives the same depth.
BARYCENTRIC_TOLERANCE = 1e-5
# Vertices closer than this (scene units) to the camera plane make a triangle's projection
# unbounded: it is binned into every tile instead of being projected.
CAMERA_PLANE_EPSILON = 1e-6
MINIMUM_CAPACITY = 1024
# Small meshes (primitives) are padded to this many triangles to share one compilation.
MINIMUM_TRIANGLES = 1024


@struct.dataclass
class MeshDepth:
  """Per-pixel nearest-triangle hits, leading shape [N, H, W].

  Attributes:
    z_depth: float32 distance along the camera's optical axis; +inf where no triangle is hit.
    distance: float32 distance along the (unit) pixel ray; +inf where no triangle is hit.
    hit: bool, a triangle is hit.
    triangle_index: int32 index into the mesh's faces; -1 where no triangle is hit.
    overflow: [N] bool: the camera's (triangle, tile) list was longer than the capacity, so
      triangles may be missing (never set by `render_mesh_depth`).
  """

  z_depth: jax.Array
  distance: jax.Array
  hit: jax.Array
  triangle_index: jax.Array
  overflow: jax.Array


def _tile_plane_coordinates(cameras: camera_lib.Cameras, camera_index, tile_size: int,
                            undistort: bool) -> tuple[jax.Array, jax.Array]:
  """Undistorted OpenCV normalised coordinates (x right, y down) of every pixel-centre ray
  (`undistort` False: of ideal pinholes, whatever their distortion coefficients say).

  Returns:
    plane: [tiles_down, tiles_across, tile_size * tile_size, 2]. The grid is padded to whole
      tiles by repeating the last row and column, so padding never widens a tile's ray range.
    on_plane: [tiles_down, tiles_across, tile_size * tile_size] bool, the ray meets the z = 1
      plane: all but a fisheye's rays 90 degrees or more off the axis, which hit nothing here
      (their z-depth would not be positive; `lens.undistort` clamps their coordinates).
  """
  tiles_down = -(-cameras.height // tile_size)
  tiles_across = -(-cameras.width // tile_size)
  rows = jnp.minimum(jnp.arange(tiles_down * tile_size), cameras.height - 1) + 0.5
  columns = jnp.minimum(jnp.arange(tiles_across * tile_size), cameras.width - 1) + 0.5
  rows, columns = jnp.meshgrid(rows.astype(jnp.float32), columns.astype(jnp.float32),
                               indexing="ij")
  x_distorted = (columns - cameras.cx[camera_index]) / cameras.fx[camera_index]
  y_distorted = (rows - cameras.cy[camera_index]) / cameras.fy[camera_index]
  distortion = cameras.distortion[camera_index]
  # Same rays as `camera.pixel_rays`.
  if cameras.fisheye:
    x, y = lens.undistort(x_distorted, y_distorted, distortion, fisheye=True)
    on_plane = lens.fisheye_angle(x_distorted, y_distorted,
                                        distortion) < lens.MAX_PLANE_ANGLE
  else:
    x, y = x_distorted, y_distorted
    if undistort:  # The Newton iterations are skipped for an ideal pinhole.
      x, y = jax.lax.cond(jnp.any(distortion != 0),
                          lambda: lens.undistort(x_distorted, y_distorted, distortion),
                          lambda: (x_distorted, y_distorted))
    on_plane = jnp.ones_like(x, bool)
  plane = jnp.stack([x, y], -1).reshape(tiles_down, tile_size, tiles_across, tile_size, 2)
  on_plane = on_plane.reshape(tiles_down, tile_size, tiles_across, tile_size)
  pixels_per_tile = tile_size * tile_size
  return (jnp.swapaxes(plane, 1, 2).reshape(tiles_down, tiles_across, pixels_per_tile, 2),
          jnp.swapaxes(on_plane, 1, 2).reshape(tiles_down, tiles_across, pixels_per_tile))


def _from_tiles(array: jax.Array, height: int, width: int, tile_size: int) -> jax.Array:
  """[tiles_down, tiles_across, tile_size * tile_size] -> [height, width] (padding dropped)."""
  tiles_down, tiles_across = array.shape[:2]
  array = array.reshape(tiles_down, tiles_across, tile_size, tile_size)
  array = jnp.swapaxes(array, 1, 2).reshape(tiles_down * tile_size, tiles_across * tile_size)
  return array[:height, :width]


def _camera_frame(triangles: jax.Array, cameras: camera_lib.Cameras, camera_index) -> jax.Array:
  """[F, 3, 3] world-space corners -> the camera's OpenCV frame (x right, y down, z forward)."""
  camera_to_world = cameras.camera_to_world[camera_index]
  corners = (triangles - camera_to_world[:, 3]) @ camera_to_world[:, :3]
  return corners * jnp.array([1.0, -1.0, -1.0], jnp.float32)


def _tile_ranges(corners: jax.Array, plane: jax.Array):
  """The block of tiles each triangle can cover (steps 1 and 2 of the module docstring).

  Args:
    corners: [F, 3, 3] triangle corners in the camera's OpenCV frame.
    plane: [tiles_down, tiles_across, P, 2] the rays' normalised coordinates.
  Returns:
    first, last: [F, 2] int32 (tile column, tile row) of the block's corners; empty blocks have
      last < first.
  """
  # Monotone bounds per tile column (x) and tile row (y): a running max of the upper bounds and a
  # reversed running min of the lower bounds only widen the ranges, so binning stays conservative.
  column_low = jax.lax.cummin(plane[..., 0].min(axis=(0, 2)), reverse=True)
  column_high = jax.lax.cummax(plane[..., 0].max(axis=(0, 2)))
  row_low = jax.lax.cummin(plane[..., 1].min(axis=(1, 2)), reverse=True)
  row_high = jax.lax.cummax(plane[..., 1].max(axis=(1, 2)))

  depth = corners[..., 2]
  in_front = depth > CAMERA_PLANE_EPSILON
  projected = corners[..., :2] / jnp.where(in_front, depth, 1.0)[..., None]  # [F, 3, 2]
  low, high = projected.min(axis=1), projected.max(axis=1)
  # Wider than the hit test's barycentric tolerance, so binning stays conservative.
  margin = 10 * BARYCENTRIC_TOLERANCE * (high - low) + 1e-7
  all_in_front = jnp.all(in_front, axis=1, keepdims=True)
  some_in_front = jnp.any(depth > 0, axis=1, keepdims=True)
  unbounded = jnp.where(some_in_front, jnp.inf, -jnp.inf)
  low = jnp.where(all_in_front, low - margin, -unbounded)
  high = jnp.where(all_in_front, high + margin, unbounded)

  def block(axis_low, axis_high, triangle_low, triangle_high):
    # Tiles with high >= triangle_low and low <= triangle_high.
    first = jnp.searchsorted(axis_high, triangle_low, side="left")
    last = jnp.searchsorted(axis_low, triangle_high, side="right") - 1
    return first, last

  first_column, last_column = block(column_low, column_high, low[:, 0], high[:, 0])
  first_row, last_row = block(row_low, row_high, low[:, 1], high[:, 1])
  first = jnp.stack([first_column, first_row], -1).astype(jnp.int32)
  last = jnp.stack([last_column, last_row], -1).astype(jnp.int32)
  return first, last


def _pair_counts(first, last, num_triangles):
  """[F] int32 number of tiles in each triangle's block; 0 for padding past `num_triangles`."""
  size = jnp.maximum(last - first + 1, 0)
  return jnp.where(jnp.arange(first.shape[0]) < num_triangles, size[:, 0] * size[:, 1], 0)


def _pair_depths(corners: jax.Array, triangle: jax.Array, pixel_plane: jax.Array,
                 candidate: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Ray-triangle intersections of (triangle, tile) pairs.

  In the camera frame every ray starts at 0 with direction d = (x, y, 1), so the ray parameter
  t is the z-depth. Moller-Trumbore against (v0, v0 + e1, v0 + e2) with the ray-independent
  parts precomputed per triangle:
    det = d . (e2 x e1),  u = d . (e2 x s) / det,  v = d . (s x e1) / det,
    t = e2 . (s x e1) / det,  with s = -v0.

  Args:
    corners: [F, 3, 3] the triangles in the camera frame (OpenCV axes).
    triangle: [C] int32, each pair's triangle.
    pixel_plane: [C, P, 2] z = 1 plane coordinates of the pixels of each pair's tile.
    candidate: [C, P] bool, pixels that may be hit (a real pair, a pixel with a plane point).
  Returns:
    hits [C, P] bool and depths [C, P] z-depth (+inf where nothing is hit).
  """
  start = -corners[:, 0]
  edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
  start_cross_edge1 = jnp.cross(start, edge1)
  normals = jnp.stack([jnp.cross(edge2, edge1), jnp.cross(edge2, start), start_cross_edge1],
                      1)[triangle]  # [C, 3 (det, u, v), 3]
  t_numerator = jnp.sum(edge2 * start_cross_edge1, axis=-1)[triangle][:, None]
  # d . n = x n_x + y n_y + n_z, for the determinant, u and v normals at once.
  products = (jnp.einsum("cpk,cnk->cnp", pixel_plane, normals[..., :2])
              + normals[..., 2:3])  # [C, 3, P]
  determinant = products[:, 0]
  # Fold the determinant's sign into the numerators so no division decides a hit.
  sign = jnp.where(determinant < 0, -1.0, 1.0)
  scale = jnp.abs(determinant)
  tolerance = BARYCENTRIC_TOLERANCE * scale
  u, v, t = products[:, 1] * sign, products[:, 2] * sign, t_numerator * sign
  hits = (candidate & (scale > 0) & (u >= -tolerance) & (v >= -tolerance)
          & (u + v <= scale + tolerance) & (t > 0))
  return hits, jnp.where(hits, t / jnp.where(scale > 0, scale, 1.0), jnp.inf)


def _single_camera_depth(triangles: jax.Array, num_triangles, cameras: camera_lib.Cameras,
                         camera_index, tile_size: int, capacity: int, undistort: bool
                         ) -> MeshDepth:
  """Mesh depth for one camera; the first `num_triangles` of [F, 3, 3] `triangles` count."""
  plane, on_plane = _tile_plane_coordinates(cameras, camera_index, tile_size, undistort)
  corners = _camera_frame(triangles, cameras, camera_index)
  first, last = _tile_ranges(corners, plane)
  counts = _pair_counts(first, last, num_triangles)
  ends = jnp.cumsum(counts)

  # Pair p belongs to the triangle whose [start, end) range of the running count contains p.
  pair = jnp.arange(capacity, dtype=jnp.int32)
  triangle = jnp.minimum(jnp.searchsorted(ends, pair, side="right"), triangles.shape[0] - 1)
  valid = pair < ends[-1]
  local = pair - (ends[triangle] - counts[triangle])
  block_width = jnp.maximum(last[triangle, 0] - first[triangle, 0] + 1, 1)
  tiles_down, tiles_across, pixels_per_tile = plane.shape[:3]
  tile_column = jnp.clip(first[triangle, 0] + local % block_width, 0, tiles_across - 1)
  tile_row = jnp.clip(first[triangle, 1] + local // block_width, 0, tiles_down - 1)

  hits, depths = _pair_depths(corners, triangle, plane[tile_row, tile_column],
                              valid[:, None] & on_plane[tile_row, tile_column])

  pixel = ((tile_row * tiles_across + tile_column)[:, None] * pixels_per_tile
           + jnp.arange(pixels_per_tile))  # [C, P] flat index into the tiled buffer
  buffer_size = tiles_down * tiles_across * pixels_per_tile
  nearest = jnp.full(buffer_size, jnp.inf, jnp.float32).at[pixel].min(depths)
  # Among the hits at the winning depth, the lowest triangle index (deterministic ties).
  no_triangle = triangles.shape[0]
  winners = hits & (depths == nearest[pixel])
  triangle_index = jnp.full(buffer_size, no_triangle, jnp.int32).at[pixel].min(
      jnp.where(winners, triangle[:, None], no_triangle))

  height, width = cameras.height, cameras.width
  unflatten = lambda array: _from_tiles(array.reshape(tiles_down, tiles_across, pixels_per_tile),
                                        height, width, tile_size)
  z_depth = unflatten(nearest)
  hit = jnp.isfinite(z_depth)
  ray_length = jnp.sqrt(1.0 + jnp.sum(plane**2, axis=-1))  # |d| = 1 / cos_to_optical_axis
  return MeshDepth(
      z_depth=z_depth,
      distance=z_depth * _from_tiles(ray_length, height, width, tile_size),
      hit=hit,
      triangle_index=jnp.where(hit, unflatten(triangle_index), -1),
      overflow=ends[-1] > capacity,
  )


@functools.partial(jax.jit, static_argnames=("tile_size", "undistort"))
def count_pairs(triangles: jax.Array, cameras: camera_lib.Cameras, tile_size: int = 4,
                num_triangles=None, undistort: bool = True) -> jax.Array:
  """[N] int32: the length of each camera's (triangle, tile) list, i.e. the capacity it needs.

  Arguments as for `mesh_depth`.
  """
  triangles = jnp.asarray(triangles, jnp.float32)
  num_triangles = triangles.shape[0] if num_triangles is None else num_triangles

  def count(camera_index):
    plane, _ = _tile_plane_coordinates(cameras, camera_index, tile_size, undistort)
    first, last = _tile_ranges(_camera_frame(triangles, cameras, camera_index), plane)
    return jnp.sum(_pair_counts(first, last, num_triangles))

  return jax.lax.map(count, jnp.arange(cameras.num_cameras))


@functools.partial(jax.jit, static_argnames=("tile_size", "capacity", "undistort"))
def mesh_depth(triangles: jax.Array, cameras: camera_lib.Cameras, tile_size: int = 4,
               capacity: int = 65536, num_triangles=None, undistort: bool = True) -> MeshDepth:
  """Nearest-triangle depth for every camera with a fixed pair capacity (jit-compatible).

  Args:
    triangles: [F, 3, 3] float32 world-space triangle corners (`Mesh.triangles`).
    cameras: N cameras; distortion is honoured (see the module docstring).
    tile_size: tile side in pixels.
    capacity: length of the (triangle, tile) list; exact where `overflow` is False.
    num_triangles: None, or an int32 scalar (traced): only the first `num_triangles` triangles
      exist, the rest is padding (so meshes padded to one size share a compilation).
    undistort: False only where every camera is an ideal pinhole (zero distortion): the
      undistortion is then not compiled (a third of this function's compilation; the same
      depths).
  Returns:
    MeshDepth with leading shape [N, H, W] (`overflow`: [N]).
  """
  triangles = jnp.asarray(triangles, jnp.float32)
  num_triangles = triangles.shape[0] if num_triangles is None else num_triangles
  render = lambda index: _single_camera_depth(triangles, num_triangles, cameras, index,
                                              tile_size, capacity, undistort)
  # One camera at a time bounds memory by one camera's pair list.
  return jax.lax.map(render, jnp.arange(cameras.num_cameras))


def render_mesh_depth(mesh: mesh_lib.Mesh | jax.Array, cameras: camera_lib.Cameras,
                      tile_size: int = 4) -> MeshDepth:
  """Exact nearest-triangle depth for every camera, sizing the pair list itself.

  A first jitted pass counts the (triangle, tile) pairs. The triangle count and the pair list's
  capacity are padded up to the next of 1, 1.25, 1.5 or 1.75 times a power of two, so similar
  meshes and views reuse one compilation and at most a fifth of either is padding. Inside a
  larger jitted function call `mesh_depth` with a fixed capacity instead.

  Args:
    mesh: a `Mesh` or its [F, 3, 3] triangles.
    cameras: N cameras.
    tile_size: tile side in pixels.
  Returns:
    MeshDepth with leading shape [N, H, W].
  """
  triangles = np.asarray(mesh.triangles if isinstance(mesh, mesh_lib.Mesh) else mesh, np.float32)
  num_triangles = triangles.shape[0]
  padded_size = _bucket(max(num_triangles, MINIMUM_TRIANGLES))
  padding = np.broadcast_to(triangles[:1], (padded_size - num_triangles, 3, 3))
  triangles = jnp.asarray(np.concatenate([triangles, padding]))
  num_triangles = jnp.int32(num_triangles)
  # Known here, on the host: synthetic cameras (the reference views) are ideal pinholes.
  undistort = bool(np.any(np.asarray(cameras.distortion) != 0))
  needed = int(jnp.max(count_pairs(triangles, cameras, tile_size, num_triangles, undistort)))
  capacity = _bucket(max(needed, MINIMUM_CAPACITY))
  return mesh_depth(triangles, cameras, tile_size, capacity, num_triangles, undistort)


def _bucket(size: int) -> int:
  """`size` rounded up to 1, 1.25, 1.5 or 1.75 times a power of two."""
  step = 1 << max(size.bit_length() - 3, 0)
  return -(-size // step) * step
