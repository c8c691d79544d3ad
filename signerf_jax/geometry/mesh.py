"""Proxy meshes: loading and validation, similarity transforms, and primitive proxies.

A proxy is a triangle mesh placed in the normalised scene frame (see `signerf_jax.data.Dataset`).
Meshes are loaded with trimesh, which triangulates polygon faces on load (a quad becomes two
triangles, a pentagon three, as a fan) and merges the geometries of a scene file (GLB, multi-object
OBJ) into one mesh in world coordinates. Everything downstream only sees `Mesh`: float32 vertices
and int32 triangle indices.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import trimesh

from signerf_jax.errors import InputError

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")


@dataclasses.dataclass(frozen=True)
class Mesh:
  """A triangle mesh.

  Attributes:
    vertices: [V, 3] float32 positions in scene units.
    faces: [F, 3] int32 vertex indices of the triangles.
    source: where it came from (a file path or a primitive's name), for error messages.
  """

  vertices: np.ndarray
  faces: np.ndarray
  source: str = ""

  @property
  def triangles(self) -> np.ndarray:
    """[F, 3, 3] float32 corner positions of every triangle."""
    return self.vertices[self.faces]

  @property
  def bounds(self) -> np.ndarray:
    """[2, 3] (minimum corner, maximum corner)."""
    return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

  def to_trimesh(self) -> trimesh.Trimesh:
    return trimesh.Trimesh(self.vertices.astype(np.float64), self.faces, process=False)


def from_trimesh(geometry: trimesh.Trimesh, source: str = "") -> Mesh:
  """Wraps a trimesh mesh (after checking it) as a `Mesh`."""
  mesh = Mesh(np.asarray(geometry.vertices, np.float32), np.asarray(geometry.faces, np.int32),
              source)
  validate(mesh)
  return mesh


def validate(mesh: Mesh) -> None:
  """Raises InputError (naming `mesh.source`) unless the mesh is a usable triangle mesh.

  Usable: at least one vertex and one triangle, all vertices finite, triangle indices in range,
  and not every triangle degenerate (zero area), which would make it invisible to every camera.
  """
  source = mesh.source or None
  if mesh.vertices.ndim != 2 or mesh.vertices.shape[0] == 0 or mesh.vertices.shape[1] != 3:
    raise InputError("mesh has no vertices", source, "vertices")
  if not np.all(np.isfinite(mesh.vertices)):
    raise InputError("mesh has non-finite (nan or inf) vertex coordinates", source, "vertices")
  if mesh.faces.ndim != 2 or mesh.faces.shape[0] == 0 or mesh.faces.shape[1] != 3:
    raise InputError("mesh has no faces (a point cloud cannot be a proxy)", source, "faces")
  if mesh.faces.min() < 0 or mesh.faces.max() >= mesh.vertices.shape[0]:
    raise InputError("face indices out of range of the vertex list", source, "faces")
  triangles = mesh.triangles.astype(np.float64)
  areas = np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0],
                                  triangles[:, 2] - triangles[:, 0]), axis=-1)
  if not np.any(areas > 0):
    raise InputError("every face has zero area", source, "faces")


def load_mesh(path: str | os.PathLike) -> Mesh:
  """Loads an OBJ/PLY/GLB/glTF/STL/OFF file as one triangle mesh.

  Scene files are flattened: every geometry is moved by its scene-graph transform and the results
  are concatenated. Polygon faces arrive triangulated. Vertices are kept as written (trimesh's
  vertex merging is disabled) so vertex indices stay those of the file.

  Raises:
    InputError: the file is missing, unreadable, not a mesh (e.g. a point cloud), or fails
      `validate`.
  """
  path = Path(path)
  if not path.is_file():
    raise InputError("mesh file not found", path)
  if path.suffix.lower() not in MESH_SUFFIXES:
    raise InputError(f"unsupported mesh format (expected one of {', '.join(MESH_SUFFIXES)})", path)
  try:
    loaded = trimesh.load(path, process=False)
  except Exception as error:  # trimesh raises many exception types for corrupt files.
    raise InputError(f"not a readable mesh ({type(error).__name__}: {error})", path) from None
  if isinstance(loaded, trimesh.Scene):
    parts = [geometry for geometry in loaded.dump() if isinstance(geometry, trimesh.Trimesh)]
    if not parts:
      raise InputError("no triangles could be read: not a mesh file of this format, or one "
                       "without faces", path, "faces")
    loaded = trimesh.util.concatenate(parts)
  if not isinstance(loaded, trimesh.Trimesh):
    raise InputError(f"contains a {type(loaded).__name__}, not a triangle mesh", path, "faces")
  return from_trimesh(loaded, str(path))


def similarity_transform(scale=1.0, rotation=None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
  """The [4, 4] matrix x -> translation + scale * rotation @ x.

  Args:
    scale: positive scalar (a uniform scale keeps the proxy's shape).
    rotation: None (identity), a [3, 3] rotation matrix, or [3] Euler angles in degrees applied
      about the fixed x, then y, then z axes.
    translation: [3] in scene units.
  """
  if np.ndim(scale) != 0 or not float(scale) > 0:
    raise InputError(f"scale must be a positive number, got {scale!r}", field="scale")
  if rotation is None:
    rotation_matrix = np.eye(3)
  elif np.shape(rotation) == (3,):
    angles = np.deg2rad(np.asarray(rotation, np.float64))
    rotation_matrix = trimesh.transformations.euler_matrix(*angles, axes="sxyz")[:3, :3]
  else:
    rotation_matrix = np.asarray(rotation, np.float64)
    if rotation_matrix.shape != (3, 3) or not np.allclose(
        rotation_matrix.T @ rotation_matrix, np.eye(3), atol=1e-5) or np.linalg.det(
            rotation_matrix) < 0:
      raise InputError("rotation must be a proper [3, 3] rotation matrix or 3 Euler angles",
                       field="rotation")
  matrix = np.eye(4)
  matrix[:3, :3] = float(scale) * rotation_matrix
  matrix[:3, 3] = np.asarray(translation, np.float64)
  return matrix


def transform_mesh(mesh: Mesh, matrix) -> Mesh:
  """The mesh with every vertex mapped by the [4, 4] affine `matrix` (computed in float64)."""
  matrix = np.asarray(matrix, np.float64)
  vertices = mesh.vertices.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
  return dataclasses.replace(mesh, vertices=vertices.astype(np.float32))


def place_on_ground(mesh: Mesh, position, size: float, up=(0.0, 0.0, 1.0),
                    mesh_up=(0.0, 1.0, 0.0), heading_degrees: float = 0.0) -> Mesh:
  """Stands a mesh on a ground plane: scaled, rotated upright, and its lowest point at `position`.

  Args:
    mesh: the proxy in its own frame.
    position: [3] scene point the mesh's footprint centre lands on (the ground height is its
      coordinate along `up`).
    size: the largest side of the mesh's own bounding box after scaling, in scene units.
    up: [3] the scene's up direction.
    mesh_up: [3] the mesh's own up direction (the shared meshes are +y up).
    heading_degrees: rotation about `up` after standing the mesh upright.
  Returns:
    The transformed mesh.
  """
  up = _unit(up, "up")
  rotation = upright_rotation(up, mesh_up, heading_degrees)
  extent = float(np.max(mesh.bounds[1] - mesh.bounds[0]))
  if not extent > 0:
    raise InputError("mesh has zero extent and cannot be scaled", mesh.source or None, "vertices")
  rotated = transform_mesh(mesh, similarity_transform(size / extent, rotation))
  centre = rotated.bounds.astype(np.float64).mean(axis=0)
  # The lowest vertex along `up` (not the bounding box corner) so any up direction works.
  lowest = float(np.min(rotated.vertices.astype(np.float64) @ up))
  footprint = centre - (np.dot(centre, up) - lowest) * up
  return transform_mesh(rotated, similarity_transform(1.0, None, np.asarray(position) - footprint))


def upright_rotation(up, mesh_up=(0.0, 1.0, 0.0), heading_degrees: float = 0.0) -> np.ndarray:
  """The [3, 3] rotation `place_on_ground` turns a mesh by: its `mesh_up` onto `up` (the
  shortest arc), then `heading_degrees` about `up`."""
  up = _unit(up, "up")
  heading = trimesh.transformations.rotation_matrix(np.deg2rad(heading_degrees), up)[:3, :3]
  return heading @ _rotation_between(_unit(mesh_up, "mesh_up"), up)


def heading_degrees_of(rotation, mesh_up=(0.0, 1.0, 0.0)) -> tuple[np.ndarray, float]:
  """The inverse of `upright_rotation`: (up [3], heading in degrees) of a [3, 3] rotation."""
  rotation = np.asarray(rotation, np.float64)
  up = rotation @ _unit(mesh_up, "mesh_up")
  turn = rotation @ upright_rotation(up, mesh_up).T  # A rotation about `up`.
  across = np.cross(up, np.eye(3)[np.argmin(np.abs(up))])
  across /= np.linalg.norm(across)
  turned = turn @ across
  return up, float(np.degrees(np.arctan2(np.dot(up, np.cross(across, turned)),
                                         np.dot(across, turned))))


def _unit(vector, field: str) -> np.ndarray:
  vector = np.asarray(vector, np.float64)
  norm = np.linalg.norm(vector)
  if vector.shape != (3,) or not norm > 0:
    raise InputError(f"must be a non-zero 3-vector, got {vector.tolist()}", field=field)
  return vector / norm


def _rotation_between(source: np.ndarray, target: np.ndarray) -> np.ndarray:
  """The [3, 3] rotation taking unit `source` to unit `target` (the shortest arc)."""
  axis = np.cross(source, target)
  cosine = float(np.clip(np.dot(source, target), -1.0, 1.0))
  if np.linalg.norm(axis) < 1e-9:
    if cosine > 0:
      return np.eye(3)
    # Opposite vectors: half a turn about any axis orthogonal to them.
    helper = np.eye(3)[np.argmin(np.abs(source))]
    axis = np.cross(source, helper)
  return trimesh.transformations.rotation_matrix(np.arccos(cosine), axis)[:3, :3]
