"""Placing a selection by pointing at training views (`signerf place`): a proxy stands on the
surface under a pixel (its ray into the trained NeRF gives the point, at the median termination
depth; a robust plane fit to the surface around it the support; the proxy stands upright along
the surface normal), or a box is triangulated from rectangles drawn in two views.

The result is a `SelectionConfig` in the dataset's own units (frame "source"), so the numbers
printed and saved are those the user's capture uses, and the edit places the proxy exactly as
the figure shows it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.data import poses as poses_lib
from signerf_jax.data.dataset import Dataset
from signerf_jax.editing import figures
from signerf_jax.editing import select as select_lib
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.errors import InputError
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import mesh_depth, placement, primitives
from signerf_jax.nerf import render

# A pixel the NeRF renders with less opacity than this shows no surface to stand on.
MIN_ACCUMULATION = 0.5
# The window of pixels the support plane is fitted to: this fraction of the view's height.
WINDOW_FRACTION = 0.04
DEFAULT_SIZE_FRACTION = 0.3
# The fields of a SelectionConfig that say where each kind of selection is.
PLACEMENT_FIELDS = {"box": ("kind", "frame", "box_min", "box_max"),
                    "proxy": ("kind", "proxy", "frame", "ground_position", "up", "ground_size",
                              "heading_degrees", "mesh_up")}


@dataclasses.dataclass(frozen=True)
class Placement:
  """Where a picked pixel puts a proxy.

  Attributes:
    view: index of the training view.
    pixel: (x, y) in that view's pixels as the run loads them.
    position: [3] the support point, scene frame.
    up: [3] unit surface normal (towards the camera), scene frame.
    size: the proxy's largest side, scene units.
    plane: the support plane fit (inlier share and residual say how flat the surface was).
    world_from_source: [4, 4] the dataset's similarity into the scene frame.
  """

  view: int
  pixel: tuple[float, float]
  position: np.ndarray
  up: np.ndarray
  size: float
  plane: placement.Plane
  world_from_source: np.ndarray

  def selection(self, proxy: str, heading_degrees: float = 0.0,
                mesh_up=(0.0, 1.0, 0.0)) -> SelectionConfig:
    """The proxy selection standing on the support, in the dataset's own units."""
    source_from_world = np.linalg.inv(np.asarray(self.world_from_source, np.float64))
    position = poses_lib.transform_points(source_from_world, self.position)
    up = source_from_world[:3, :3] @ self.up
    scale = poses_lib.similarity_scale(self.world_from_source)
    return SelectionConfig(
        kind="proxy", proxy=proxy, frame="source",
        ground_position=tuple(round(float(value), 6) for value in position),
        up=tuple(round(float(value), 6) for value in up / np.linalg.norm(up)),
        ground_size=round(self.size / scale, 6), heading_degrees=heading_degrees,
        mesh_up=tuple(mesh_up))


def locate(model, variables, dataset: Dataset, view: int, pixel: tuple[float, float], *,
           size: float | None = None, size_fraction: float = DEFAULT_SIZE_FRACTION,
           seed: int = 0) -> Placement:
  """The support under `pixel` of training view `view`.

  Args:
    model, variables: the trained NeRF.
    dataset: its training views (scene frame).
    view: index of the view in `dataset`.
    pixel: (x, y) pixel coordinates in that view (0..width, 0..height).
    size: the proxy's largest side in the dataset's own units; None: `size_fraction` of the
      view's height at the picked point's depth.
    seed: seeds the plane fit.
  Raises:
    InputError naming the parameter: a view or pixel outside the dataset, or a pixel where the
    NeRF shows no surface.
  """
  cameras = dataset.cameras
  if not 0 <= view < cameras.num_cameras:
    raise InputError(f"must be 0 .. {cameras.num_cameras - 1}, got {view}", field="view")
  x, y = (float(value) for value in pixel)
  if not (0 <= x < cameras.width and 0 <= y < cameras.height):
    raise InputError(f"({x:g}, {y:g}) is outside the {cameras.width}x{cameras.height} view",
                     field="pixel")
  radius = max(2, round(WINDOW_FRACTION * cameras.height))
  xs, ys = placement.window_pixels(x, y, cameras.width, cameras.height, radius)
  rays = camera_lib.pixel_rays(cameras, np.full(xs.shape, view), xs, ys)
  rendered = render.render_rays_chunked(model, variables, rays, chunk_size=1024)
  return support(dataset, view, (x, y), rays, rendered, size=size, size_fraction=size_fraction,
                 seed=seed)


def support(dataset: Dataset, view: int, pixel: tuple[float, float], rays: camera_lib.Rays,
            rendered, *,
            size: float | None = None, size_fraction: float = DEFAULT_SIZE_FRACTION,
            seed: int = 0) -> Placement:
  """`locate` from the rendered window: rays [K] through the picked `pixel` first, then the
  window's (`placement.window_pixels`), and the NeRF's `accumulation` and `median_depth` [K]
  along them."""
  accumulation = np.asarray(rendered["accumulation"])
  origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
  x, y = pixel
  if accumulation[0] < MIN_ACCUMULATION:
    raise InputError(f"the NeRF shows no surface at ({x:.1f}, {y:.1f}) of view {view} (opacity "
                     f"{accumulation[0]:.2f}): pick a pixel on the support", field="pixel")
  z_depth = np.asarray(rendered["median_depth"])
  distance = z_depth / np.asarray(rays.cos_to_optical_axis)
  points = origins + directions * distance[:, None]
  solid = accumulation[1:] >= MIN_ACCUMULATION
  plane = placement.fit_plane(points[1:][solid], points[0],
                              placement.RELATIVE_THRESHOLD * float(distance[0]), seed)
  plane = placement.orient(plane, origins[0])
  if size is None:
    scene_size = size_fraction * dataset.cameras.height * float(z_depth[0]) / float(
        dataset.cameras.fy[view])
  else:
    scene_size = size * poses_lib.similarity_scale(dataset.world_from_source)
  return Placement(view, (x, y), plane.point, plane.normal, scene_size, plane,
                   np.asarray(dataset.world_from_source, np.float64))


def box_selection(dataset: Dataset, views, rectangles) -> SelectionConfig:
  """The box selection around what pixel `rectangles` ([V, 4] x0, y0, x1, y1) drawn in training
  `views` ([V] indices, at least two) all see (`placement.frusta_box` inside the scene's
  bounds), in the dataset's own units: the box around the source-frame corners."""
  views = np.asarray(views, np.int64)
  if np.any(views < 0) or np.any(views >= dataset.num_images):
    raise InputError(f"views must be 0 .. {dataset.num_images - 1}, got {views.tolist()}",
                     field="view")
  box = placement.frusta_box(dataset.cameras.take(views), rectangles, dataset.scene_bounds)
  corners = np.stack(np.meshgrid(*box.T, indexing="ij"), -1).reshape(-1, 3)
  source = poses_lib.transform_points(
      np.linalg.inv(np.asarray(dataset.world_from_source, np.float64)), corners)
  return SelectionConfig(kind="box", frame="source",
                         box_min=tuple(round(float(value), 6) for value in source.min(0)),
                         box_max=tuple(round(float(value), 6) for value in source.max(0)))


def selection_mesh(selection: SelectionConfig, dataset: Dataset) -> mesh_lib.Mesh:
  """The selection as the edit builds it, as a mesh in the scene frame (a box's as a cuboid)."""
  if selection.kind == "proxy":
    return select_lib.place_proxy(selection, dataset.views)
  box = select_lib.make_box(selection, dataset.views)
  lower, upper = np.asarray(box.minimum, np.float64), np.asarray(box.maximum, np.float64)
  return mesh_lib.transform_mesh(primitives.box(tuple(upper - lower)),
                                 mesh_lib.similarity_transform(1.0, None, (lower + upper) / 2))


def placement_figure(dataset: Dataset, view: int, selection: SelectionConfig,
                     pixel: tuple[float, float] | None = None) -> np.ndarray:
  """[H, W, 3] the view with the selection's silhouette tinted and outlined in red (and the
  picked pixel marked in yellow): where the edit will put it, before any diffusion runs."""
  hit = np.asarray(mesh_depth.render_mesh_depth(selection_mesh(selection, dataset),
                                                dataset.cameras.take(np.asarray([view]))).hit[0])
  image = np.asarray(dataset.images[view], np.float32).copy()
  red = np.asarray([1.0, 0.1, 0.1], np.float32)
  image[hit] = 0.55 * image[hit] + 0.45 * red
  image = figures.outline(image, hit, red)
  if pixel is not None:
    column, row = int(pixel[0]), int(pixel[1])
    arm = max(2, dataset.cameras.height // 50)
    image[row, max(column - arm, 0):column + arm + 1] = [1.0, 1.0, 0.0]
    image[max(row - arm, 0):row + arm + 1, column] = [1.0, 1.0, 0.0]
  return image


def _scene_from_frame(selection: SelectionConfig, dataset: Dataset) -> np.ndarray:
  """[4, 4] the similarity from the selection's frame into the scene frame."""
  if selection.frame == "source":
    return np.asarray(dataset.world_from_source, np.float64)
  return np.eye(4)


def handle_pose(selection: SelectionConfig, dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
  """Where an interactive handle (the viewer's gizmo) of the selection sits, in the scene frame:
  (rotation [3, 3], position [3]). A box's handle is its centre, axis-aligned; a proxy's is its
  ground point, turned as the proxy is (`geometry.mesh.upright_rotation`: the proxy's own up
  along the handle's `mesh_up`). `moved_selection` inverts it."""
  scene_from_frame = _scene_from_frame(selection, dataset)
  if selection.kind == "box":
    centre = (np.asarray(selection.box_min, np.float64) + np.asarray(selection.box_max)) / 2
    return np.eye(3), poses_lib.transform_points(scene_from_frame, centre)
  if selection.ground_position is None:
    raise InputError("a proxy placed by scale, rotation and translation has no ground point to "
                     "move: place it with --on_ground (or `signerf place`)",
                     field="ground_position")
  rotation = scene_from_frame[:3, :3] / poses_lib.similarity_scale(scene_from_frame)
  own = mesh_lib.upright_rotation(select_lib.up_direction(selection, dataset.views),
                                  selection.mesh_up, selection.heading_degrees)
  return rotation @ own, poses_lib.transform_points(scene_from_frame, selection.ground_position)


def moved_selection(selection: SelectionConfig, dataset: Dataset, rotation, position
                    ) -> SelectionConfig:
  """The selection whose handle (`handle_pose`) is at `position` [3] turned by `rotation`
  [3, 3], both in the scene frame, in the selection's own frame (a box only moves: it stays
  axis-aligned in its frame)."""
  frame_from_scene = np.linalg.inv(_scene_from_frame(selection, dataset))
  centre = poses_lib.transform_points(frame_from_scene, np.asarray(position, np.float64))
  rounded = lambda values: tuple(round(float(value), 6) for value in values)
  if selection.kind == "box":
    half = (np.asarray(selection.box_max, np.float64) - np.asarray(selection.box_min)) / 2
    return dataclasses.replace(selection, box_min=rounded(centre - half),
                               box_max=rounded(centre + half))
  turn = frame_from_scene[:3, :3] / poses_lib.similarity_scale(frame_from_scene)
  up, heading = mesh_lib.heading_degrees_of(turn @ np.asarray(rotation, np.float64),
                                            selection.mesh_up)
  return dataclasses.replace(selection, ground_position=rounded(centre), up=rounded(up),
                             heading_degrees=round(heading, 4))


def stand_on_surface(model, variables, dataset: Dataset, selection: SelectionConfig
                     ) -> SelectionConfig:
  """The proxy stood on the NeRF's surface under its ground point (`locate`, as `signerf
  place` does), seen from the training view that looks at that point most steeply along the
  proxy's down direction (its ray falls onto the support, not past it); its size, heading and
  own up are kept.

  Raises:
    InputError: no training view sees the ground point, or the NeRF shows no surface there.
  """
  rotation, point = handle_pose(selection, dataset)
  pixels, depth = (np.asarray(value) for value in camera_lib.project(dataset.cameras, point))
  cameras = dataset.cameras
  inside = ((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < cameras.width)
            & (pixels[:, 1] >= 0) & (pixels[:, 1] < cameras.height))
  if not inside.any():
    raise InputError("no training view sees the proxy's ground point", field="ground_position")
  down = -(rotation @ np.asarray(selection.mesh_up, np.float64))
  down /= np.linalg.norm(down)
  sight = point - np.asarray(cameras.positions, np.float64)
  steepness = (sight @ down) / np.linalg.norm(sight, axis=1)
  view = int(np.argmax(np.where(inside, steepness, -np.inf)))
  size = selection.ground_size
  if selection.frame == "scene":
    size /= poses_lib.similarity_scale(dataset.world_from_source)
  found = locate(model, variables, dataset, view, tuple(map(float, pixels[view])), size=size)
  placed = found.selection(selection.proxy, selection.heading_degrees, selection.mesh_up)
  return dataclasses.replace(selection, **{name: getattr(placed, name)
                                           for name in PLACEMENT_FIELDS["proxy"]})
