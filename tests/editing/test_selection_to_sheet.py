"""End to end on a synthetic scene's ground truth: selection -> reference cameras -> sheet."""

import numpy as np
import pytest

from signerf_jax.data import synthetic, synthetic_render
from signerf_jax.editing import crops
from signerf_jax.editing import sheet
from signerf_jax.geometry import control_depth
from signerf_jax.geometry import masks
from signerf_jax.geometry import mesh as mesh_lib
from signerf_jax.geometry import mesh_depth
from signerf_jax.geometry import primitives
from signerf_jax.geometry import reference_cameras
from signerf_jax.geometry import selection

TILE = 32
LAYOUT = sheet.SheetLayout(tile_height=TILE, tile_width=TILE)


@pytest.fixture(scope="module")
def scene_and_views():
  scene = synthetic.make_scene(seed=3, settings=synthetic.SceneSettings(num_meshes=0))
  rig = synthetic_render.CameraRig(num_views=10, image_size=40)
  cameras = synthetic_render.make_cameras(rig, scene.scene_bounds)
  rgb, depth, object_ids = synthetic_render.render(scene, cameras)
  return scene, cameras, rgb, depth, object_ids


def test_box_around_an_object_selects_its_pixels_and_builds_a_sheet(scene_and_views):
  scene, cameras, rgb, depth, object_ids = scene_and_views
  target = scene.objects[0]
  lower, upper = target.world_bounds()
  box = selection.Box.create(lower - 0.02, upper + 0.02)
  # The ground truth's 0 = "nothing here" counts as no surface.
  selected = selection.shape_selection(cameras, box, depth)
  mask = np.asarray(selected.mask)
  assert mask[object_ids == target.object_id].all()
  assert not mask[object_ids == 0][depth[object_ids == 0] == 0].any()  # background

  reference, report = reference_cameras.place_reference_cameras(
      cameras, np.asarray(box.corners), count=LAYOUT.num_tiles, width=64, height=64)
  assert report.dataset_views_seeing_selection >= 1
  assert np.all(report.fill_ratio > 0)
  # Reference views rendered from the ground truth, as a NeRF would render them.
  reference_rgb, reference_depth, _ = synthetic_render.render(scene, reference)
  reference_selection = selection.shape_selection(reference, box, reference_depth)
  center, radius = reference_cameras.selection_sphere(np.asarray(box.corners))
  near, far = control_depth.selection_depth_range(reference, center, radius)
  control = control_depth.normalize_control_depth(reference_selection.control_depth, near, far)
  dilated = masks.dilate_and_feather(reference_selection.mask, radius=16.0)
  boxes = crops.selection_crop_boxes(reference, box.corners, TILE, TILE)
  tiles = [crops.crop_to_tiles(image, boxes, TILE, TILE, fill_value=fill)
           for image, fill in ((reference_rgb, 0.5), (np.asarray(control)[..., None], 0.0),
                               (np.asarray(dilated)[..., None], 0.0))]
  sheet_rgb, sheet_control, sheet_mask = sheet.reference_sheet_inputs(*tiles, LAYOUT)
  assert sheet_rgb.shape == (2 * TILE, 3 * TILE, 3)
  mask_tiles, _ = sheet.disassemble(sheet_mask, LAYOUT)
  assert np.all(np.asarray(mask_tiles).reshape(LAYOUT.num_tiles, -1).max(axis=1) > 0)

  # The slot update for the dataset views that see the selection.
  empty = masks.views_with_empty_masks(mask)
  visible = np.setdiff1d(np.arange(cameras.num_cameras), empty)
  near, far = control_depth.selection_depth_range(cameras, center, radius)
  view_control = control_depth.normalize_control_depth(selected.control_depth, near, far)
  view_boxes = crops.selection_crop_boxes(cameras, box.corners, TILE, TILE)[visible]
  view_tiles = [crops.crop_to_tiles(image[visible], view_boxes, TILE, TILE)
                for image in (rgb, np.asarray(view_control)[..., None],
                              mask[..., None].astype(np.float32))]
  slot_rgb, _, slot_mask = sheet.slot_update_inputs(sheet_rgb, sheet_control, *view_tiles,
                                                    layout=LAYOUT)
  assert slot_rgb.shape == (len(visible), 2 * TILE, 3 * TILE, 3)
  tiles_mask, slots_mask = zip(*(sheet.disassemble(m, LAYOUT) for m in slot_mask))
  assert not np.any(np.stack(tiles_mask))
  assert np.all(np.stack(slots_mask).reshape(len(visible), -1).max(axis=1) > 0)


@pytest.mark.slow
def test_proxy_on_the_free_spot_is_visible_where_nothing_hides_it(scene_and_views):
  scene, cameras, _, depth, _ = scene_and_views
  proxy = mesh_lib.place_on_ground(primitives.box((1.0, 1.0, 1.0)), scene.free_spot_center,
                                   size=scene.free_spot_radius)
  proxy_depth = mesh_depth.render_mesh_depth(proxy, cameras)
  selected = selection.proxy_selection(cameras, depth, proxy_depth.z_depth)
  mask = np.asarray(selected.mask)
  hit = np.asarray(proxy_depth.hit)
  assert mask.any() and np.all(mask <= hit)
  # Where the proxy is masked, the control depth is the proxy's; elsewhere the scene's.
  control = np.asarray(selected.control_depth)
  np.testing.assert_allclose(control[mask], np.asarray(proxy_depth.z_depth)[mask])
  scene_pixels = ~mask & (depth > 0)
  np.testing.assert_allclose(control[scene_pixels], depth[scene_pixels], rtol=1e-5)
