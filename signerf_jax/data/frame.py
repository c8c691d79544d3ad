"""The scene frame: where a capture's content is, found from its cameras (and SfM points).

A NeRF models a region in detail (the *inner region*, [-1, 1]^3 in scene units) and, for
unbounded scenes, everything beyond it contracted (mip-NeRF 360). Centring that region on the
camera positions cuts off what the cameras look at; so the frame is found from the data:

  * object-centric captures ("unbounded": cameras around the content, real background): the
    centre is the point nearest all optical axes in the least-squares sense (what the cameras
    look at), moved to the median of the SfM points most views see near their image centre
    when the source has points. The inner region's half-side is the cameras' largest distance
    from that centre, so every camera and everything between them is modelled in detail and
    only the distant background is contracted (mip-NeRF 360's and nerfacto's choice).
  * forward-facing captures (every camera within 45 degrees of the mean viewing direction):
    LLFF's normalisation: the average pose becomes the identity and the box around every
    view's frustum between its near and far content depths (from the source, or from SfM
    points) is scaled onto [-1, 1]^3.
  * bounded scenes (a transparent or known constant background) come with their frame.

The map from the source's frame is a similarity `world_from_source` (x_scene = s R x + t), so
anything a user gives in the dataset's own units (a box, a proxy placement) converts exactly.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Literal

import numpy as np

from signerf_jax.camera import Cameras
from signerf_jax.data import poses as poses_lib
from signerf_jax.errors import InputError

SceneKind = Literal["bounded", "forward_facing", "unbounded"]
SCENE_KINDS = typing.get_args(SceneKind)
KIND_DESCRIPTIONS = {
    "bounded": "bounded object (constant background)",
    "forward_facing": "forward-facing capture",
    "unbounded": "object-centric 360-degree capture, background contracted",
}
FORWARD_FACING_MAX_ANGLE_DEGREES = 45.0
# Rays start this fraction of the cameras' distance to the centre past the lens when no SfM
# points tell where the nearest content is (nerfacto: 0.05 with cameras at distance ~1).
DEFAULT_NEAR_FRACTION = 0.05
# With SfM points: the near plane is this fraction of the nearest content depth any view has
# (its 1st percentile, robust to stray points), so nothing real is clipped.
NEAR_CONTENT_FRACTION = 0.5
NEAR_CONTENT_PERCENTILE = 1.0
# Far end of unbounded rays (scene units); the contraction maps it next to the grid's border.
UNBOUNDED_FAR = 1000.0
# SfM points "near an image centre" lie within this fraction of the half-width / half-height.
CENTRAL_FRACTION = 0.3
MIN_CENTRAL_POINTS = 8
# LLFF's per-view content depth range from points: these percentiles of visible z-depths.
DEPTH_PERCENTILES = (0.1, 99.9)
# Projections of at most this many points are used (a random subset beyond).
MAX_POINTS = 20000
# Cameras whose positions all lie within this fraction of their coordinates' size of their
# centroid stand at one position (`cameras_stationary`): ~8 steps of float32's rounding (1.2e-7),
# the precision cameras are stored in, so only copies of one position and their rounding count.
STATIONARY_FRACTION = 1e-6


@dataclasses.dataclass(frozen=True)
class SceneFrame:
  """A capture's normalised scene frame.

  Attributes:
    kind: one of SCENE_KINDS.
    world_from_source: [4, 4] float64 similarity from the source frame into the scene frame.
    bounds: [2, 3] float64 (min, max) of the inner region, scene units.
    near, far: ray range in scene units.
    method: how the frame was found (for the printed summary), e.g. "optical axes + SfM points".
  """

  kind: str
  world_from_source: np.ndarray
  bounds: np.ndarray
  near: float
  far: float
  method: str = "given"

  def __post_init__(self):
    if self.kind not in SCENE_KINDS:
      raise ValueError(f"scene kind must be one of {SCENE_KINDS}, got {self.kind!r}")

  @property
  def scale(self) -> float:
    """Scene units per source unit."""
    return poses_lib.similarity_scale(self.world_from_source)

  def describe(self) -> dict[str, Any]:
    """JSON-friendly: kind, and the inner region's centre and half-side in source units."""
    source_from_world = np.linalg.inv(self.world_from_source)
    centre = poses_lib.transform_points(source_from_world, self.bounds.mean(axis=0))
    half_sides = (self.bounds[1] - self.bounds[0]) / 2 / self.scale
    return {"kind": self.kind, "method": self.method,
            "center_in_source_units": centre.round(6).tolist(),
            "half_size_in_source_units": half_sides.round(6).tolist(),
            "scene_units_per_source_unit": round(self.scale, 9),
            "near": self.near, "far": self.far}

def summary_line(description: dict[str, Any]) -> str:
  """One line for the command line, from `SceneFrame.describe()`."""
  centre = ", ".join(f"{value:.3g}" for value in description["center_in_source_units"])
  half = ", ".join(f"{value:.3g}" for value in description["half_size_in_source_units"])
  return (f"scene frame: {KIND_DESCRIPTIONS[description['kind']]}; region modelled in detail "
          f"centred at ({centre}), half-size ({half}) in the dataset's units "
          f"({description['method']}); rays {description['near']:.3g}..{description['far']:.3g} "
          "scene units")


def classify(cameras: Cameras) -> str:
  """"forward_facing" when every camera looks within 45 degrees of the mean direction, else
  "unbounded" (cameras around the content)."""
  forwards = np.asarray(cameras.forward, np.float64)
  mean = forwards.mean(axis=0)
  mean /= max(np.linalg.norm(mean), 1e-12)
  return ("forward_facing" if np.min(forwards @ mean) > np.cos(
      np.radians(FORWARD_FACING_MAX_ANGLE_DEGREES)) else "unbounded")


def nearest_point_to_axes(cameras: Cameras) -> np.ndarray:
  """[3] the point with the least summed squared distance to every camera's optical axis.

  Solves sum_i (I - d_i d_i^T) p = sum_i (I - d_i d_i^T) o_i. Parallel axes (a translating
  camera) leave it undetermined along their direction; a tiny ridge towards the cameras'
  centroid picks the solution nearest it.
  """
  origins = np.asarray(cameras.positions, np.float64)
  directions = np.asarray(cameras.forward, np.float64)
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  projectors = np.eye(3) - directions[:, :, None] * directions[:, None, :]
  system = projectors.sum(axis=0)
  right_side = np.einsum("nij,nj->i", projectors, origins)
  ridge = 1e-6 * np.trace(system) / 3
  centroid = origins.mean(axis=0)
  return np.linalg.solve(system + ridge * np.eye(3), right_side + ridge * centroid)


def _project(cameras: Cameras, points: np.ndarray):
  """Pinhole projection (distortion ignored: used for statistics only).

  Returns:
    normalised offsets [N, P, 2] from the principal point in units of half the image size, and
    z-depths [N, P].
  """
  camera_to_world = np.asarray(cameras.camera_to_world, np.float64)
  local = np.einsum("nji,npj->npi", camera_to_world[:, :, :3],
                    points[None] - camera_to_world[:, None, :, 3])
  depth = -local[..., 2]
  safe_depth = np.where(depth > 1e-9, depth, 1e-9)
  x = local[..., 0] / safe_depth * np.asarray(cameras.fx)[:, None]
  y = -local[..., 1] / safe_depth * np.asarray(cameras.fy)[:, None]
  offsets = np.stack([x / (cameras.width / 2), y / (cameras.height / 2)], axis=-1)
  return offsets, depth


def _subsample(points: np.ndarray) -> np.ndarray:
  if len(points) <= MAX_POINTS:
    return points
  return points[np.random.default_rng(0).choice(len(points), MAX_POINTS, replace=False)]


def central_content(cameras: Cameras, points: np.ndarray) -> np.ndarray | None:
  """[3] median of the SfM points seen near the image centre by the most views, or None when
  too few points are (the cameras do not share a central subject)."""
  points = _subsample(np.asarray(points, np.float64))
  offsets, depth = _project(cameras, points)
  central = (depth > 0) & np.all(np.abs(offsets) < CENTRAL_FRACTION, axis=-1)
  seen_by = central.mean(axis=0)
  if not np.any(seen_by > 0):
    return None
  chosen = points[seen_by >= 0.5 * seen_by.max()]
  if len(chosen) < MIN_CENTRAL_POINTS:
    return None
  return np.median(chosen, axis=0)


def visible_depth_bounds(cameras: Cameras, points: np.ndarray) -> np.ndarray | None:
  """[N, 2] per view, the DEPTH_PERCENTILES of the z-depths of the points inside its image
  (LLFF's `imgs2poses` bounds), or None when some view sees no point."""
  points = _subsample(np.asarray(points, np.float64))
  offsets, depth = _project(cameras, points)
  inside = (depth > 0) & np.all(np.abs(offsets) <= 1.0, axis=-1)
  bounds = []
  for view_depths, view_inside in zip(depth, inside):
    if not np.any(view_inside):
      return None
    bounds.append(np.percentile(view_depths[view_inside], DEPTH_PERCENTILES))
  return np.asarray(bounds)


def _up_rotation(cameras: Cameras) -> np.ndarray:
  """The rotation taking the cameras' mean up vector onto +z (nerfstudio's orientation)."""
  up = np.asarray(cameras.camera_to_world, np.float64)[:, :, 1].mean(axis=0)
  if np.linalg.norm(up) < 1e-6:
    return np.eye(3)
  return poses_lib.rotation_between(up, [0.0, 0.0, 1.0])


def cameras_stationary(cameras: Cameras) -> bool:
  """Whether every camera stands at (nearly) one position (`STATIONARY_FRACTION`): their views
  then show no parallax, and nothing in them tells where the scene is or how far it reaches."""
  positions = np.asarray(cameras.positions, np.float64)
  spread = float(np.max(np.linalg.norm(positions - positions.mean(axis=0), axis=-1)))
  return spread <= STATIONARY_FRACTION * float(np.max(np.abs(positions)))


def _stationary_error(cameras: Cameras) -> InputError:
  """The error for cameras at one position that nothing else places a region around (the
  loader adds the dataset's path)."""
  position = ", ".join(f"{value:.6g}" for value in np.asarray(cameras.positions[0], np.float64))
  return InputError(
      f"all {cameras.num_cameras} cameras stand at one position ({position}): the cameras do "
      "not move, so the views show no parallax and the scene's position and size cannot be "
      "inferred from them; give the region to model in the dataset's units with --scene_center "
      "X Y Z and --scene_radius R")


def _region_centre(cameras: Cameras, points, object_sphere, scene_center, scene_radius
                   ) -> tuple[np.ndarray, list[str]]:
  """The inner region's centre (source units) and how it was found (`object_centric_frame`'s
  arguments): given, the object sphere's, or where the optical axes meet (SfM points refine it).
  """
  if scene_center is not None:
    return np.asarray(scene_center, np.float64), ["centre given"]
  if object_sphere is not None:
    return np.asarray(object_sphere[0], np.float64), ["object sphere"]
  refined = None if points is None else central_content(cameras, points)
  if refined is not None:
    return refined, ["optical axes", "SfM points"]
  if scene_radius is None and cameras_stationary(cameras):
    # The axes of cameras at one position meet there: the region would shrink to the rounding
    # noise of their coordinates.
    raise _stationary_error(cameras)
  return nearest_point_to_axes(cameras), ["optical axes"]


def object_centric_frame(cameras: Cameras, *, points=None, object_sphere=None,
                         scene_center=None, scene_radius=None) -> SceneFrame:
  """The frame of a 360-degree capture (see the module docstring).

  Args:
    cameras: source-frame cameras.
    points: None or [P, 3] SfM points (refine the centre, find the nearest content).
    object_sphere: None or (centre, radius) the source gives for its object: used as the
      centre (the inner region still reaches the cameras).
    scene_center, scene_radius: overrides in source units (the inner region's centre and
      half-side).
  Raises:
    InputError: the cameras stand at one position (`cameras_stationary`) and nothing else
      (points, an object sphere, scene_center, scene_radius) places the region.
  """
  centre, method = _region_centre(cameras, points, object_sphere, scene_center, scene_radius)
  positions = np.asarray(cameras.positions, np.float64)
  distances = np.linalg.norm(positions - centre, axis=-1)
  rotation = _up_rotation(cameras)
  if scene_radius is not None:
    half_side = float(scene_radius)
    method.append("radius given")
  else:
    # Cameras inside the L-inf cube: their largest offset along any axis after rotation.
    half_side = float(np.max(np.abs((positions - centre) @ rotation.T)))
  if not half_side > 0:
    raise InputError(f"the inner region must have a positive size, got {half_side}",
                     field="scene_radius")
  scale = 1.0 / half_side
  world_from_source = poses_lib.similarity(scale, rotation, -scale * rotation @ centre)
  reach = float(np.median(distances))
  if reach <= STATIONARY_FRACTION * half_side:
    # Cameras at the region's centre (a panorama with --scene_radius): start rays a fraction
    # of the region's size out rather than at the lens (near 0 breaks disparity spacing).
    reach = half_side
  near = DEFAULT_NEAR_FRACTION * reach * scale
  if points is not None and len(points):
    _, depth = _project(cameras, _subsample(np.asarray(points, np.float64)))
    in_front = np.where(depth > 0, depth, np.inf)
    nearest = np.percentile(in_front, NEAR_CONTENT_PERCENTILE, axis=1)
    if np.all(np.isfinite(nearest)):
      near = min(near, NEAR_CONTENT_FRACTION * float(np.min(nearest)) * scale)
  bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
  return SceneFrame("unbounded", world_from_source, bounds, float(near), UNBOUNDED_FAR,
                    " + ".join(method))


def forward_facing_frame(cameras: Cameras, depth_bounds: np.ndarray) -> SceneFrame:
  """LLFF's normalisation: the average pose becomes the identity (cameras look down -z, y up),
  then the box around every view's frustum between its near and far z-depths (`depth_bounds`
  [N, 2], source units) is centred and scaled onto [-1, 1]^3."""
  camera_to_world = np.asarray(cameras.camera_to_world, np.float64)
  focal = np.stack([np.asarray(cameras.fx), np.asarray(cameras.fy)], -1).astype(np.float64)
  # Half the field of view as normalised image coordinates (x, y) of the image corner.
  corner = np.array([cameras.width / 2, cameras.height / 2]) / focal
  frustum_points = _frustum_corners(camera_to_world, corner, depth_bounds).reshape(-1, 3)
  centre = camera_to_world[:, :, 3].mean(0)
  average_rotation = poses_lib.mean_rotation(camera_to_world)
  average_from_source = poses_lib.similarity(1.0, average_rotation.T,
                                             -average_rotation.T @ centre)
  points = poses_lib.transform_points(average_from_source, frustum_points)
  world_from_source = poses_lib.unit_box_similarity(points.min(0),
                                                    points.max(0)) @ average_from_source
  scene_points = poses_lib.transform_points(world_from_source, frustum_points)
  scale = poses_lib.similarity_scale(world_from_source)
  near = scale * np.min(depth_bounds[:, 0])
  # The bounds are z-depths: the ray through an image corner travels 1/cos further.
  far = scale * np.max(depth_bounds[:, 1] * np.sqrt(1 + np.sum(corner**2, -1)))
  bounds = np.stack([scene_points.min(0), scene_points.max(0)])
  return SceneFrame("forward_facing", world_from_source, bounds, float(near), float(far),
                    "average pose + frustum depth range")


def _frustum_corners(camera_to_world: np.ndarray, corner: np.ndarray,
                     depth_bounds: np.ndarray) -> np.ndarray:
  """[N, 8, 3] world corners of each view's frustum between its near and far z-depths.

  Args:
    camera_to_world: [N, 3, 4] OpenGL poses.
    corner: [N, 2] normalised (x, y) of the image corner.
    depth_bounds: [N, 2] near and far z-depths.
  """
  signs = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]], np.float64)
  xy = corner[:, None, :] * signs  # [N, 4, 2]
  # A point at z-depth d along normalised (x, y) is d * (x, y, -1) in OpenGL camera space.
  directions = np.concatenate([xy, -np.ones_like(xy[..., :1])], -1)
  local = depth_bounds[:, :, None, None] * directions[:, None]  # [N, 2, 4, 3]
  world = np.einsum("nij,nabj->nabi", camera_to_world[:, :, :3], local)
  return (world + camera_to_world[:, None, None, :, 3]).reshape(-1, 8, 3)


def guessed_depth_bounds(cameras: Cameras) -> np.ndarray:
  """[N, 2] a content depth range for forward-facing cameras without points: from the axes'
  nearest point when it lies in front of the cameras (distance d: d / 4 .. 4 d), else from
  the cameras' spread (10x .. 1000x)."""
  positions = np.asarray(cameras.positions, np.float64)
  focus = nearest_point_to_axes(cameras)
  depths = np.einsum("ni,ni->n", focus - positions, np.asarray(cameras.forward, np.float64))
  if np.all(depths > 0):
    typical = float(np.median(depths))
  else:
    typical = 100.0 * max(float(np.max(np.std(positions, axis=0))), 1e-6)
  return np.tile([typical / 4, typical * 4], (cameras.num_cameras, 1))


def estimate_frame(cameras: Cameras, *, kind: str | None = None, points=None,
                   depth_bounds=None, object_sphere=None, scene_center=None,
                   scene_radius=None) -> SceneFrame:
  """The scene frame of a capture from its (source-frame) cameras and what else it knows.

  Args:
    cameras: every view of the capture (train and held-out share the frame).
    kind: None infers it (`classify`); "forward_facing" or "unbounded" forces it.
    points: None or [P, 3] SfM points.
    depth_bounds: None or [N, 2] per-view content z-depth ranges (forward-facing).
    object_sphere: None or (centre [3], radius) of the object of interest.
    scene_center, scene_radius: overrides of the inner region in source units (unbounded
      scenes).
  Raises:
    InputError: an unknown kind, or "bounded" (bounded scenes come with their frame); cameras
      that stand at one position with nothing else to place the region
      (`cameras_stationary`).
  """
  overrides_region = scene_center is not None or scene_radius is not None
  if (kind is None and overrides_region and depth_bounds is None and points is None
      and cameras_stationary(cameras)):
    # Cameras at one position give no forward-facing frame (no parallax to find depths
    # from); the region the user gives is what the stationary-camera error asks for.
    kind = "unbounded"
  kind = kind or classify(cameras)
  if kind == "forward_facing":
    if scene_center is not None or scene_radius is not None:
      raise InputError("a forward-facing frame follows from the views' depth ranges; "
                       "scene_center / scene_radius apply to unbounded scenes",
                       field="scene_center")
    method = "source depth range"
    if depth_bounds is None and points is not None:
      depth_bounds, method = visible_depth_bounds(cameras, points), "SfM point depths"
    if depth_bounds is None:
      if cameras_stationary(cameras):
        # The guess scales a frustum box by the cameras' spread: zero here.
        raise _stationary_error(cameras)
      depth_bounds, method = guessed_depth_bounds(cameras), "guessed from the optical axes"
    frame = forward_facing_frame(cameras, np.asarray(depth_bounds, np.float64))
    return dataclasses.replace(frame, method=f"{frame.method} ({method})")
  if kind == "unbounded":
    return object_centric_frame(cameras, points=points, object_sphere=object_sphere,
                                scene_center=scene_center, scene_radius=scene_radius)
  raise InputError(f"cannot estimate a {kind!r} frame from cameras (must be one of "
                   "forward_facing, unbounded)", field="scene_kind")
