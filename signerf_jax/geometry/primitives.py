"""Primitive proxies built with trimesh: box, sphere, cylinder, capsule and a primitive cow.

All are centred at the origin. The cylinder and capsule stand along +y and the primitive cow
follows the shared spot cow's frame (+y up, head towards -z, about the same bounding box), so
the proxy-fidelity ablation (spot high-poly / spot low-poly / primitives) can place all three
with the same transform.
"""

from __future__ import annotations

import numpy as np
import trimesh

from signerf_jax.errors import InputError
from signerf_jax.geometry import mesh as mesh_lib

# Cylinders and capsules are built along z by trimesh; this turns z into y.
_Z_TO_Y = trimesh.transformations.rotation_matrix(-np.pi / 2, (1.0, 0.0, 0.0))


def _checked_positive(**values: float) -> None:
  for name, value in values.items():
    if not float(value) > 0:
      raise InputError(f"must be positive, got {value!r}", field=name)


def box(extents=(1.0, 1.0, 1.0)) -> mesh_lib.Mesh:
  """An axis-aligned box with the given [3] side lengths (12 triangles)."""
  _checked_positive(**{f"extents[{i}]": value for i, value in enumerate(extents)})
  return mesh_lib.from_trimesh(trimesh.creation.box(extents=extents), "primitive:box")


def sphere(radius: float = 0.5, subdivisions: int = 3) -> mesh_lib.Mesh:
  """An icosphere inscribed in the sphere of `radius` (20 * 4**subdivisions triangles)."""
  _checked_positive(radius=radius)
  return mesh_lib.from_trimesh(trimesh.creation.icosphere(subdivisions, radius),
                               "primitive:sphere")


def cylinder(radius: float = 0.5, height: float = 1.0, sections: int = 32) -> mesh_lib.Mesh:
  """A closed cylinder along +y."""
  _checked_positive(radius=radius, height=height)
  geometry = trimesh.creation.cylinder(radius, height, sections=sections, transform=_Z_TO_Y)
  return mesh_lib.from_trimesh(geometry, "primitive:cylinder")


def capsule(radius: float = 0.25, height: float = 1.0, count=(16, 16)) -> mesh_lib.Mesh:
  """A capsule along +y; `height` is the total length including both hemispherical caps."""
  _checked_positive(radius=radius, height=height)
  if height < 2 * radius:
    raise InputError(f"height {height} is less than the diameter {2 * radius}", field="height")
  geometry = trimesh.creation.capsule(height - 2 * radius, radius, count=list(count),
                                      transform=_Z_TO_Y)
  return mesh_lib.from_trimesh(geometry, "primitive:capsule")


def primitive_cow() -> mesh_lib.Mesh:
  """A box body, four cylinder legs and a sphere head, shaped like the spot cow.

  Same frame as `spot_triangulated.obj` (+y up, head towards -z) and about the same bounding
  box, so it can stand in for spot in the proxy-fidelity ablation. The parts overlap (a union of
  closed solids, not one manifold), which ray casting and depth rendering do not mind.
  """
  body = trimesh.creation.box(bounds=[[-0.36, -0.30, -0.30], [0.36, 0.42, 0.95]])
  legs = [
      trimesh.creation.cylinder(0.11, 0.5, sections=16, transform=_Z_TO_Y).apply_translation(
          (x, -0.49, z)) for x in (-0.22, 0.22) for z in (-0.15, 0.8)
  ]
  head = trimesh.creation.icosphere(2, 0.3).apply_translation((0.0, 0.58, -0.38))
  geometry = trimesh.util.concatenate([body, *legs, head])
  return mesh_lib.from_trimesh(geometry, "primitive:cow")
