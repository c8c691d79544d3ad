"""The object catalogue of the default model's data, and standing one object on the ground.

Kinds, in catalogue order (label: caption nouns; geometry):
  cow:      "cow"; the spot cow (meshes/spot/spot_triangulated.obj), or, when the shared meshes are
            absent, the primitive cow of `signerf_jax.geometry.primitives` (a box, legs, a head);
  bunny:    "bunny", "rabbit"; meshes/bunny_lowpoly.obj (only with the shared meshes);
  teddy:    "teddy bear"; meshes/teddy.obj (only with the shared meshes);
  teapot:   "teapot"; meshes/teapot.obj (only with the shared meshes);
  cube:     "cube", "box"; the exact box of `raycast`;
  ball:     "ball", "sphere"; the exact sphere;
  cylinder: "cylinder"; the exact capped cylinder;
  cone:     "cone"; a trimesh cone (flat shaded);
  torus:    "torus", "ring", "donut"; a trimesh torus lying flat;
  capsule:  "capsule", "pill"; a trimesh capsule standing up.
The shared meshes come from $SIGNERF_SHARED_DATA/meshes (default ../shared/data/meshes next to
the repository), looked up when the catalogue is built, so the data generator also runs without
them (primitives and the primitive cow only).

Every kind lives in the canonical frame of `signerf_jax.data.synthetic` (z up, inside [-1, 1]^3,
resting on z = -1). An object is placed with a yaw, a footprint radius r on the ground (its
widest horizontal extent) and a height stretch; its *object coordinates* (where its appearance's
pattern lives) are the placed frame without the yaw, centred at its base and scaled so r = 1.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import numpy as np
import trimesh

from signerf_jax.data import poses as poses_lib
from signerf_jax.data import raycast
from signerf_jax.data import synthetic
from signerf_jax.default_model import appearance as appearance_lib
from signerf_jax.geometry import primitives

KINDS = ("cow", "bunny", "teddy", "teapot", "cube", "ball", "cylinder", "cone", "torus", "capsule")
KIND_NOUNS: dict[str, tuple[str, ...]] = {
    "cow": ("cow",), "bunny": ("bunny", "rabbit"), "teddy": ("teddy bear",),
    "teapot": ("teapot",), "cube": ("cube", "box"), "ball": ("ball", "sphere"),
    "cylinder": ("cylinder",), "cone": ("cone",), "torus": ("torus", "ring", "donut"),
    "capsule": ("capsule", "pill"),
}
SHARED_MESH_FILES = {"cow": "spot/spot_triangulated.obj", "bunny": "bunny_lowpoly.obj",
                     "teddy": "teddy.obj", "teapot": "teapot.obj"}
# A shape is at most this many footprint radii tall (as the synthetic scenes' objects).
MAX_HEIGHT_IN_RADII = 3.0
_Y_UP_FROM_Z_UP = trimesh.transformations.rotation_matrix(-np.pi / 2, (1.0, 0.0, 0.0))


def default_mesh_directory() -> Path:
  """$SIGNERF_SHARED_DATA/meshes, else ../shared/data/meshes next to the repository (read now)."""
  shared = os.environ.get("SIGNERF_SHARED_DATA",
                          Path(__file__).resolve().parents[3] / "shared" / "data")
  return Path(shared) / "meshes"


@dataclasses.dataclass(frozen=True)
class ObjectKind:
  """One kind of object the data shows.

  Attributes:
    name: the label (one of KINDS).
    nouns: what captions call it.
    shape: the `synthetic` shape ("sphere", "box", "cylinder" or "mesh").
    source: where the geometry comes from (an OBJ path or "primitive:<name>").
    footprint_extent: largest horizontal distance of the canonical shape from its z axis.
    height_stretch_range: (min, max) of the vertical scale over the horizontal scale.
    file_to_canonical, clusters: the canonical mesh (meshes only).
  """

  name: str
  nouns: tuple[str, ...]
  shape: str
  source: str
  footprint_extent: float
  height_stretch_range: tuple[float, float] = (1.0, 1.0)
  file_to_canonical: np.ndarray | None = None
  clusters: raycast.TriangleClusters | None = None


def _mesh_kind(name: str, canonical: tuple[np.ndarray, raycast.TriangleClusters], source: str,
               height_stretch_range=(1.0, 1.0)) -> ObjectKind:
  """A mesh kind from `synthetic.canonical_mesh`'s (file_to_canonical, clusters)."""
  file_to_canonical, clusters = canonical
  extent = float(np.max(np.linalg.norm(clusters.corners[..., :2], axis=-1)))
  return ObjectKind(name, KIND_NOUNS[name], "mesh", source, extent, height_stretch_range,
                    file_to_canonical, clusters)


@functools.cache
def build_catalogue(mesh_directory: str) -> tuple[ObjectKind, ...]:
  """The kinds available with the meshes in `mesh_directory` (missing files are left out)."""
  kinds = {}
  for name, relative in SHARED_MESH_FILES.items():
    path = Path(mesh_directory) / relative
    if path.is_file():
      kinds[name] = _mesh_kind(name, synthetic.load_canonical_mesh(path), str(path))
  if "cow" not in kinds:
    # Flat shading: unmerged vertices give each face its own normals (the parts are boxes).
    cow = primitives.primitive_cow().to_trimesh()
    cow.unmerge_vertices()
    kinds["cow"] = _mesh_kind("cow", synthetic.canonical_mesh(cow), "primitive:cow")
  kinds["cube"] = ObjectKind("cube", KIND_NOUNS["cube"], "box", "primitive:box", np.sqrt(2.0),
                             (0.85, 1.15))
  kinds["ball"] = ObjectKind("ball", KIND_NOUNS["ball"], "sphere", "primitive:sphere", 1.0)
  kinds["cylinder"] = ObjectKind("cylinder", KIND_NOUNS["cylinder"], "cylinder",
                                 "primitive:cylinder", 1.0, (0.6, 1.6))
  cone = trimesh.creation.cone(1.0, 2.0, sections=32, transform=_Y_UP_FROM_Z_UP)
  cone.unmerge_vertices()  # A sharp rim between the side and the base.
  kinds["cone"] = _mesh_kind("cone", synthetic.canonical_mesh(cone), "primitive:cone", (0.7, 1.4))
  torus = trimesh.creation.torus(1.0, 0.35, major_sections=40, minor_sections=16,
                                 transform=_Y_UP_FROM_Z_UP)
  kinds["torus"] = _mesh_kind("torus", synthetic.canonical_mesh(torus), "primitive:torus")
  capsule = primitives.capsule(0.5, 3.0).to_trimesh()
  kinds["capsule"] = _mesh_kind("capsule", synthetic.canonical_mesh(capsule), "primitive:capsule",
                                (0.8, 1.2))
  return tuple(kinds[name] for name in KINDS if name in kinds)


@dataclasses.dataclass(frozen=True)
class Placement:
  """Where and how big an object stands.

  Attributes:
    center: [2] footprint centre on the ground.
    footprint_radius: r, the object's widest horizontal extent from its axis.
    yaw: rotation about the vertical axis (radians).
    height_stretch: vertical scale over horizontal scale (within the kind's range).
  """

  center: np.ndarray
  footprint_radius: float
  yaw: float
  height_stretch: float


def random_placement(rng: np.random.Generator, kind: ObjectKind, center, footprint_radius: float
                     ) -> Placement:
  """A placement at `center` ([2]) with a random yaw and height stretch (within the kind's)."""
  return Placement(center=np.asarray(center, np.float64), footprint_radius=float(footprint_radius),
                   yaw=float(rng.uniform(0, 2 * np.pi)),
                   height_stretch=float(rng.uniform(*kind.height_stretch_range)))


def _scales(kind: ObjectKind, placement: Placement) -> tuple[float, float]:
  """(horizontal, vertical) scale from canonical units to the scene."""
  horizontal = placement.footprint_radius / kind.footprint_extent
  vertical = min(horizontal * placement.height_stretch,
                 MAX_HEIGHT_IN_RADII / 2 * placement.footprint_radius)
  return horizontal, vertical


def object_to_world(kind: ObjectKind, placement: Placement, ground_height: float) -> np.ndarray:
  """[4, 4] from the kind's canonical frame into the scene (standing on the ground)."""
  horizontal, vertical = _scales(kind, placement)
  yaw = trimesh.transformations.rotation_matrix(placement.yaw, (0.0, 0.0, 1.0))[:3, :3]
  linear = yaw @ np.diag([horizontal, horizontal, vertical])
  return synthetic.affine(linear, [*placement.center, ground_height + vertical])


def object_from_canonical(kind: ObjectKind, placement: Placement) -> np.ndarray:
  """[4, 4] from canonical coordinates to object coordinates (base centre 0, footprint radius 1)."""
  horizontal, vertical = _scales(kind, placement)
  radius = placement.footprint_radius
  return synthetic.affine(np.diag([horizontal, horizontal, vertical]) / radius,
                          [0.0, 0.0, vertical / radius])


def _albedo(appearance: appearance_lib.Appearance, canonical_to_object: np.ndarray,
            canonical_points: np.ndarray) -> np.ndarray:
  return appearance.albedo(poses_lib.transform_points(canonical_to_object, canonical_points))


def scene_object(kind: ObjectKind, placement: Placement, appearance: appearance_lib.Appearance,
                 object_id: int, ground_height: float = synthetic.GROUND_HEIGHT
                 ) -> synthetic.SceneObject:
  """The object as a `synthetic.SceneObject` whose albedo is `appearance` in object coordinates."""
  return synthetic.SceneObject(
      object_id=object_id, shape=kind.shape,
      object_to_world=object_to_world(kind, placement, ground_height),
      color=np.asarray(appearance_lib.PALETTE[appearance.color][0]), texture=appearance.pattern,
      texture_axis=appearance.rotation[:, 2], texture_frequency=0.0,
      footprint_center=placement.center, footprint_radius=placement.footprint_radius,
      mesh_path=kind.source if kind.shape == "mesh" else None,
      file_to_canonical=kind.file_to_canonical, clusters=kind.clusters,
      albedo_function=functools.partial(_albedo, appearance,
                                        object_from_canonical(kind, placement)))
