"""The views stage renders each training view only where the selection, its mask and the control
depth the diffusion model sees can be: the same conditioning as full frames, for fewer rays."""

from __future__ import annotations

import dataclasses
import types

import jax
import numpy as np
import pytest

from signerf_jax import camera as camera_lib
from signerf_jax.data import load_dataset, synthetic, synthetic_render
from signerf_jax.editing import conditioning, crops
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing import update as update_lib
from signerf_jax.editing.config import SelectionConfig
from signerf_jax.editing.project import save_arrays
from signerf_jax.editing.select import EditSelection
from signerf_jax.editing.stages import inputs, propagation
from signerf_jax.geometry import image_rectangles, masks
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import primitives, selection
from signerf_jax.nerf import capacity, render, sampling, scene_info
from signerf_jax.nerf import model as nerf_model

SIZE = 64
# 6 and 2 pixels at 64 pixels: the mask reaches 8 pixels beyond the selection.
DILATION, FEATHER = 48.0, 16.0


class GroundTruthRenderer:
  """`render.render_cameras`' contract (only `pixels` rendered, 0 elsewhere) on a synthetic
  scene's ground truth, recording the pixels each call asks for."""

  def __init__(self, scene):
    self.scene = scene
    self.pixels: list[np.ndarray] = []

  def __call__(self, model, variables, cameras, pixels=None, **unused):
    rgb, depth, _ = synthetic_render.render(self.scene, cameras)
    pixels = np.ones(depth.shape, bool) if pixels is None else np.asarray(pixels, bool)
    self.pixels.append(pixels)
    keep = lambda array: np.where(pixels.reshape(pixels.shape + (1,) * (array.ndim - 3)), array,
                                  0).astype(np.float32)
    return {"rgb": keep(rgb), "median_depth": keep(depth), "accumulation": keep(depth > 0)}


@pytest.fixture(scope="module")
def scene_and_cameras():
  """A synthetic scene and 6 cameras of a rig around it."""
  scene = synthetic.make_scene(seed=3, settings=synthetic.SceneSettings(num_meshes=0))
  rig = synthetic_render.CameraRig(num_views=6, image_size=SIZE)
  return scene, synthetic_render.make_cameras(rig, scene.scene_bounds)


def with_edge_cameras(cameras: camera_lib.Cameras, edit_selection) -> camera_lib.Cameras:
  """`cameras` and 3 more: the first one with its principal point moved so that the right
  border cuts the selection in half, one moved so far that the selection is out of view, and
  one at the selection's centre (its points on both sides)."""
  center = edit_selection.sphere()[0]
  pixel = np.asarray(camera_lib.project(cameras.take([0]), center)[0])[0]
  inside = np.array(cameras.camera_to_world[0])
  inside[:, 3] = center
  extra = camera_lib.Cameras.create(
      np.stack([cameras.camera_to_world[0], cameras.camera_to_world[0], inside]),
      float(cameras.fx[0]), cx=float(cameras.cx[0]) + np.array([SIZE - pixel[0], 10 * SIZE, 0]),
      cy=float(cameras.cy[0]), width=SIZE, height=SIZE)
  return jax.tree.map(lambda *parts: np.concatenate(parts), cameras, extra)


def box_selection(scene, mode="surface"):
  lower, upper = scene.objects[0].world_bounds()
  config = SelectionConfig(kind="box", box_min=tuple(lower - 0.02), box_max=tuple(upper + 0.02),
                           box_mask_mode=mode, dilation_radius=DILATION, feather_radius=FEATHER)
  return EditSelection("box", box=selection.Box.create(lower - 0.02, upper + 0.02)), config


def proxy_selection(scene):
  proxy = mesh_lib.place_on_ground(primitives.box((1.0, 1.0, 1.0)), scene.free_spot_center,
                                   size=scene.free_spot_radius)
  config = SelectionConfig(kind="proxy", proxy="primitive:box", dilation_radius=DILATION,
                           feather_radius=FEATHER)
  return EditSelection("proxy", proxy=proxy), config


def test_a_rectangle_is_the_hand_computed_projection_grown_and_clipped():
  # Looking down -z from the origin (f = 10, principal point at the centre of 40 x 40): the box
  # x in [-0.5, 0.5], y in [-0.3, 0.7], 1 to 2 units away spans image x = 20 + 10 x / depth in
  # [15, 25] and y = 20 - 10 y / depth in [13, 23]; pixel j is in when its centre j + 1/2 is.
  box = selection.Box.create([-0.5, -0.3, -2.0], [0.5, 0.7, -1.0])
  pose = lambda x, z=0.0, turn=1.0: [[turn, 0, 0, x], [0, 1, 0, 0], [0, 0, turn, z]]
  cameras = camera_lib.Cameras.create(
      np.array([pose(0.0), pose(3.0), pose(10.0), pose(0.0, turn=-1.0), pose(0.0, z=-1.5)],
               np.float32), 10.0, width=40, height=40)
  rectangles = image_rectangles.points_rectangles(cameras, box.corners, growth=3)
  # Moved 3 to the right, x in [-3.5, -2.5] spans image x in [-15, 7.5]: the left border.
  # Moved 10, the box is out of view; turned around or inside it, it is behind the camera.
  np.testing.assert_array_equal(rectangles, [[12, 10, 28, 26], [0, 10, 11, 26], [0, 0, 0, 0],
                                             [0, 0, 40, 40], [0, 0, 40, 40]])
  compiled = []
  record = lambda event, duration, **kwargs: compiled.append(event.endswith("compile_duration"))
  jax.monitoring.register_event_duration_secs_listener(record)
  try:  # Sets of 5 to 8 cameras share one program (padded to 8).
    fewer = image_rectangles.points_rectangles(cameras.take([0, 1, 2, 3, 4, 0]), box.corners, 3)
  finally:
    jax.monitoring.unregister_event_duration_listener(record)
  assert not any(compiled)
  np.testing.assert_array_equal(fewer, rectangles[[0, 1, 2, 3, 4, 0]])
  pixels = image_rectangles.rectangle_pixels(rectangles, 40, 40)
  assert pixels[0, 10, 12] and not pixels[0, 9, 12] and not pixels[0, 10, 28]
  assert pixels.reshape(5, -1).sum(1).tolist() == [16 * 16, 11 * 16, 0, 1600, 1600]
  np.testing.assert_array_equal(
      image_rectangles.box_rectangles([[14.5, -3.0, 10.0, 5.2], [-9, 30, 100, 20]], 40, 40),
      [[14, 0, 25, 2], [0, 30, 40, 40]])


@pytest.mark.parametrize("distortion", [None, (-0.3, 0.05, 0.0, 0.0), (0.25, 0.0, 0.01, 0.0)])
def test_a_rectangle_holds_every_pixel_whose_ray_meets_the_box(distortion):
  """Lens distortion bends the box's edges; the rectangle follows the cameras' own rays."""
  box = selection.Box.create([-0.2, -0.9, -2.5], [0.9, 0.1, -1.2])
  poses = np.array([[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]],
                    [[1, 0, 0, 0.4], [0, 1, 0, -0.3], [0, 0, 1, 0.2]]], np.float32)
  cameras = camera_lib.Cameras.create(poses, 30.0, width=48, height=40, distortion=distortion)
  hits = np.stack([np.asarray(sampling.ray_box_interval(rays.origins, rays.directions,
                                                        box.minimum, box.maximum)[2])
                   for rays in (camera_lib.image_rays(cameras, index) for index in range(2))])
  rows, columns = hits.any(2), hits.any(1)
  tight = np.array([[np.argmax(c), np.argmax(r), len(c) - np.argmax(c[::-1]),
                     len(r) - np.argmax(r[::-1])] for r, c in zip(rows, columns)])
  rectangles = image_rectangles.points_rectangles(cameras, box.corners, 0)
  # It holds every pixel whose ray meets the box, and at most a pixel more on each side (where
  # the box's image is narrower than its bounding rectangle).
  assert np.all(rectangles[:, :2] <= tight[:, :2]) and np.all(rectangles[:, 2:] >= tight[:, 2:])
  assert np.all(np.abs(rectangles - tight) <= 1)


def compare(full: conditioning.Conditioning, region: conditioning.Conditioning,
            rendered: np.ndarray) -> None:
  """`region` (rendered only at `rendered`) is `full` wherever anything is needed."""
  np.testing.assert_array_equal(region.selected, full.selected)
  np.testing.assert_array_equal(region.mask, full.mask)
  assert rendered[full.mask > 0].all()  # Every pixel of the mask was rendered.
  for name in ("render", "control", "control_depth"):
    np.testing.assert_array_equal(getattr(region, name)[rendered], getattr(full, name)[rendered])
  assert not region.control[~rendered].any() and np.all(region.control_depth[~rendered] == np.inf)


def condition_both(monkeypatch, scene, cameras, edit_selection, config, context_boxes=None):
  renderer = GroundTruthRenderer(scene)
  monkeypatch.setattr(render, "render_cameras", renderer)
  full = conditioning.condition(None, None, cameras, edit_selection, config)
  region = conditioning.condition(None, None, cameras, edit_selection, config,
                                  only_where_selected_can_appear=True,
                                  context_boxes=context_boxes)
  assert renderer.pixels[0].all()
  return full, region, renderer.pixels[1]


@pytest.mark.parametrize("kind", ["box", "proxy"])
def test_conditioning_near_the_selection_equals_full_frames(monkeypatch, scene_and_cameras,
                                                            kind):
  scene, cameras = scene_and_cameras
  edit_selection, config = box_selection(scene) if kind == "box" else proxy_selection(scene)
  cameras = with_edge_cameras(cameras, edit_selection)
  full, region, rendered = condition_both(monkeypatch, scene, cameras, edit_selection, config)
  compare(full, region, rendered)
  shown = full.selected.reshape(len(rendered), -1).any(1)
  assert shown[:6].sum() >= 3 and shown[6]  # The rig sees it, and the border cuts it.
  assert full.selected[6][:, -1].any() and rendered[6][:, -1].any()
  assert not shown[7] and not rendered[7].any()  # Out of view: nothing rendered.
  assert rendered[8].all()  # The camera inside the selection: the full frame.
  assert rendered[:6].mean() < 0.5
  # The control depth under the mask's dilated and feathered edge is the scene's (the ground),
  # which a rectangle smaller by the dilation radius would not render.
  edge = (full.mask > 0) & ~full.selected
  reach = conditioning.mask_reach(config, SIZE, SIZE) + conditioning.SAFETY_PIXELS
  smaller = image_rectangles.rectangle_pixels(image_rectangles.points_rectangles(
      cameras, edit_selection.points, reach - int(masks.scaled_radius(DILATION, SIZE, SIZE))),
      SIZE, SIZE)
  assert np.any(full.control[edge & ~smaller] > 0)


def test_the_update_tiles_see_the_control_of_full_frames(monkeypatch, scene_and_cameras):
  """The diffusion model sees the control depth of the whole tile: with the tiles' sources as
  context boxes, the tiles of the views that show the selection are those of full frames."""
  scene, cameras = scene_and_cameras
  edit_selection, config = box_selection(scene, mode="silhouette")
  # No mask growth: the tiles reach far beyond the selection's rectangles.
  config = dataclasses.replace(config, dilation_radius=0.0, feather_radius=0.0)
  cameras = with_edge_cameras(cameras, edit_selection)
  near_selection = conditioning.pixels_to_render(cameras, edit_selection, config)
  for tile in (8, 96):  # Crops downscaled (a wider resampling kernel) and upscaled.
    layout = sheet_lib.SheetLayout(tile_height=tile, tile_width=tile)
    boxes = update_lib.tile_boxes(cameras, layout, edit_selection.points)
    context = types.SimpleNamespace(dataset=types.SimpleNamespace(cameras=cameras),
                                    layout=layout, tile_boxes=lambda cameras, boxes=boxes: boxes)
    full, region, rendered = condition_both(monkeypatch, scene, cameras, edit_selection, config,
                                            inputs.tile_sources(context))
    compare(full, region, rendered)
    shown = np.flatnonzero(full.mask.reshape(len(boxes), -1).any(1))
    tiles = [np.asarray(crops.crop_to_tiles(conditioned.control[shown][..., None], boxes[shown],
                                            tile, tile, fill_value=0.0))
             for conditioned in (full, region)]
    np.testing.assert_array_equal(tiles[1], tiles[0])
    # Every pixel a tile is resampled from (a nonzero weight) was rendered.
    weights = jax.grad(lambda images: crops.crop_to_tiles(images, boxes[shown], tile, tile,
                                                          fill_value=0.0).sum())
    used = np.asarray(weights(np.zeros((len(shown), SIZE, SIZE, 1), np.float32)))[..., 0] > 0
    assert rendered[shown][used].all()
    assert (rendered & ~near_selection)[:6].any() and not rendered[:6].all()
    assert not rendered[7].any()


@pytest.fixture(scope="module")
def random_nerf(tiny_scene):
  """The tiny scene's training views and a NeRF of random weights for them."""
  directory, scene = tiny_scene
  dataset = load_dataset(directory, split="train")
  info = scene_info.SceneInfo.from_dataset(dataset)
  model = nerf_model.NerfModel(info, dataclasses.replace(capacity.derive_capacity(info),
                                                         mlp_width=16))
  return scene, dataset, model, nerf_model.init_variables(model, jax.random.key(0))


def test_a_nerf_conditioned_near_the_selection_matches_its_full_frames(random_nerf):
  """Through the real renderer (chunked rays of a random NeRF), in chunks of views."""
  scene, dataset, model, variables = random_nerf
  edit_selection, config = box_selection(scene, mode="silhouette")
  indices = np.arange(dataset.num_images)
  conditioned = [conditioning.Conditioning.stack_chunks([
      conditioning.condition_views(model, variables, dataset.cameras, chunk, edit_selection,
                                   config, 8, only_where_selected_can_appear=only)
      for chunk in (indices[:8], indices[8:])]) for only in (False, True)]
  rendered = conditioning.pixels_to_render(dataset.cameras, edit_selection, config)
  compare(*conditioned, rendered)
  assert conditioned[0].selected.any() and not rendered.all()


def test_chunks_of_views_find_their_pixels_to_render_with_one_program(random_nerf):
  scene, dataset, model, variables = random_nerf
  edit_selection, config = box_selection(scene, mode="silhouette")
  image_rectangles._hull_bounds.clear_cache()  # pylint: disable=protected-access
  for chunk in ([0, 1, 2, 3], [4, 5], [6]):
    conditioning.condition_views(model, variables, dataset.cameras, chunk, edit_selection,
                                 config, 4, only_where_selected_can_appear=True)
  assert image_rectangles._hull_bounds._cache_size() == 1  # pylint: disable=protected-access


def test_the_second_update_renders_the_edited_nerf_only_under_the_masks(random_nerf, tmp_path,
                                                                        monkeypatch):
  scene, dataset, model, variables = random_nerf
  edit_selection, config = box_selection(scene, mode="silhouette")
  indices = np.arange(4)
  conditioned = conditioning.condition_views(model, variables, dataset.cameras, indices,
                                             edit_selection, config, 4)
  for index in indices:
    save_arrays(tmp_path / f"{index}.npz", mask=conditioned.mask[index],
                control=conditioned.control[index])
  nerf = types.SimpleNamespace(model=model, variables=variables)
  context = types.SimpleNamespace(
      dataset=dataset, tile_boxes=lambda cameras: np.zeros((cameras.num_cameras, 4)),
      nerf=lambda iteration: nerf, view_path=lambda index: tmp_path / f"{index}.npz")
  full = render.render_cameras(model, variables, dataset.cameras.take(indices))["rgb"]
  asked, render_cameras = [], render.render_cameras
  monkeypatch.setattr(render, "render_cameras", lambda *args, pixels=None, **kwargs: (
      asked.append(pixels), render_cameras(*args, pixels=pixels, **kwargs))[1])
  views = propagation._view_loader(context, 2)(indices)
  np.testing.assert_array_equal(asked, [conditioned.mask > 0])
  weight = conditioned.mask[..., None]
  np.testing.assert_array_equal(views.images, dataset.images[indices] * (1 - weight)
                                + full * weight)
  assert conditioned.mask.any() and not conditioned.mask.all()
