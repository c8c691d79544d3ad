"""Samples: reproducible, one appearance per sheet, and images, masks and depth that agree."""

import dataclasses

import cv2
import numpy as np
import pytest

from signerf_jax import camera as camera_lib
from signerf_jax.default_model import captions, objects, samples, scenes
from signerf_jax.errors import InputError
from signerf_jax.metrics import colors

CAPTIONS = captions.CaptionSettings()


def make(settings, seed, sheet, attributes=None):
  return samples.make_sample(np.random.default_rng(seed), settings, CAPTIONS, sheet, attributes)


def cameras_of(views, size):
  intrinsics = views["intrinsics"]
  return camera_lib.Cameras.create(views["camera_to_world"], fx=intrinsics[:, 0],
                                   fy=intrinsics[:, 1], cx=intrinsics[:, 2], cy=intrinsics[:, 3],
                                   width=size, height=size)


@pytest.mark.parametrize("sheet", [False, True])
def test_samples_are_reproducible_from_the_seed(tiny_sampling, sheet):
  first, again, other = (make(tiny_sampling, seed, sheet).arrays() for seed in (3, 3, 4))
  assert first.keys() == again.keys()
  for name in first:
    np.testing.assert_array_equal(first[name], again[name], err_msg=name)
  assert np.abs(first["rgb"].astype(int) - other["rgb"]).max() > 50


@pytest.mark.parametrize("color", ["red", "green", "blue", "purple", "white", "black"])
def test_the_tiles_of_a_sheet_share_one_appearance(tiny_sampling, color):
  sample = make(tiny_sampling, 5, True, captions.Attributes("cylinder", color, "striped"))
  views = sample.views
  assert len(views["rgb"]) == tiny_sampling.sheet_tiles + 1
  means = []
  for rgb, silhouette in zip(views["rgb"], views["silhouette"]):
    pixels = rgb[silhouette > 0] / 255.0
    assert colors.dominant_color(pixels) == color
    means.append(pixels.mean(0))
  means = np.array(means)
  if color not in colors.ACHROMATIC_COLORS:
    # Lambert shading does not depend on the viewer: only which part is visible changes.
    chromaticity = means / means.sum(-1, keepdims=True)
    assert np.ptp(chromaticity, axis=0).max() < 0.08


@pytest.mark.parametrize("sheet", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_images_masks_and_depth_agree(tiny_sampling, sheet, seed):
  sample = make(tiny_sampling, seed, sheet)
  views = sample.views
  size = tiny_sampling.image_size
  silhouette = views["silhouette"] > 0
  assert np.all(silhouette.sum((1, 2)) >= tiny_sampling.min_object_pixels)
  assert np.all(views["depth"][silhouette] > 0)
  # Without shadows, the object changes only the pixels it covers.
  np.testing.assert_array_equal(views["rgb"][~silhouette], views["background_rgb"][~silhouette])
  assert np.mean(np.any(views["rgb"] != views["background_rgb"], -1)[silhouette]) > 0.5
  # Dilated silhouettes: exactly the pixels within r of the silhouette, nested.
  for view in range(len(silhouette)):
    distance = cv2.distanceTransform((~silhouette[view]).astype(np.uint8), cv2.DIST_L2,
                                     cv2.DIST_MASK_PRECISE)
    for index, radius in enumerate(tiny_sampling.dilation_radii):
      np.testing.assert_array_equal(views["dilated_silhouettes"][view, index],
                                    distance <= radius + 1e-4)
    x0, y0, x1, y1 = views["boxes"][view]
    assert silhouette[view, y0:y1, x0:x1].sum() == silhouette[view].sum()
    assert silhouette[view, y0].any() and silhouette[view, y1 - 1].any()
    assert silhouette[view, :, x0].any() and silhouette[view, :, x1 - 1].any()
  # The object's depth lies within its bounding sphere, and the control range brackets it.
  cameras = cameras_of(views, size)
  pixels, center_depth = camera_lib.project(cameras, sample.object_sphere[None, :3])
  radius = sample.object_sphere[3]
  near, far = views["control_near_far"].T
  for view in range(len(silhouette)):
    object_depth = views["depth"][view][silhouette[view]].astype(np.float64)
    assert np.all(np.abs(object_depth - center_depth[view, 0]) <= radius * 1.01)
    assert near[view] <= object_depth.min() and object_depth.max() <= far[view]
  # Reference cameras look at the object's centre.
  reference = views["view_kinds"] == samples.VIEW_KINDS.index("reference")
  np.testing.assert_allclose(np.asarray(pixels)[reference, 0], size / 2, atol=0.05)
  if sheet:
    assert np.all(reference[:tiny_sampling.sheet_tiles])


def test_sheet_slot_views_are_crop_views_at_the_set_rate(tiny_sampling):
  kinds = [make(tiny_sampling, seed, True).views["view_kinds"][-1] for seed in range(12)]
  crop = samples.VIEW_KINDS.index("crop")
  assert 0 < np.sum(np.array(kinds) == crop) < 12


@pytest.mark.parametrize("margin", [0.15, 0.6])
def test_crop_views_frame_the_object_as_the_pipelines_selection_crops(tiny_sampling, margin):
  settings = dataclasses.replace(tiny_sampling, reference_view_probability=0.0,
                                 crop_margin_range=(margin, margin))
  size = settings.image_size
  for seed in range(4):
    sample = make(settings, seed, False)
    assert sample.views["view_kinds"][0] == samples.VIEW_KINDS.index("crop")
    # The object's bounding sphere projects inside the crop, and its bounding box (before the
    # margin) spans about 1 / (1 + 2 margin) of the tile along its longer side, unless the crop
    # was shifted to stay inside the dataset frame or held at its smallest size.
    x0, y0, x1, y1 = sample.views["boxes"][0]
    extent = max(x1 - x0, y1 - y0) / size
    assert extent <= 1.0 / (1 + 2 * margin) + 2.0 / size
    assert extent >= 0.3 / (1 + 2 * margin)


def test_generator_runs_without_the_shared_meshes(monkeypatch, tmp_path):
  monkeypatch.setenv("SIGNERF_SHARED_DATA", str(tmp_path / "missing"))
  settings = scenes.SceneSampling(image_size=32, rig_views=12, min_object_pixels=8)
  catalogue = settings.catalogue()
  assert [kind.name for kind in catalogue] == [
      "cow", "cube", "ball", "cylinder", "cone", "torus", "capsule"]
  assert catalogue[0].source == "primitive:cow"
  sample = make(settings, 0, True, captions.Attributes("cow", "orange", "spotted"))
  assert sample.views["silhouette"].sum() > 0


@pytest.mark.shared_data
def test_catalogue_uses_the_shared_meshes(monkeypatch, shared_data):
  monkeypatch.setenv("SIGNERF_SHARED_DATA", str(shared_data))
  settings = scenes.SceneSampling(image_size=32, rig_views=12, min_object_pixels=8)
  catalogue = {kind.name: kind for kind in settings.catalogue()}
  assert tuple(catalogue) == objects.KINDS
  assert catalogue["cow"].source.endswith("spot_triangulated.obj")
  sample = make(settings, 1, True, captions.Attributes("cow", "red", "plain"))
  for rgb, silhouette in zip(sample.views["rgb"], sample.views["silhouette"]):
    assert colors.dominant_color(rgb[silhouette > 0] / 255.0) == "red"


@pytest.mark.parametrize("field, value", [("ground_half_size_range", (0.3, 0.5)),
                                          ("fill_range", (0.5, 0.4)), ("dilation_radii", (4, 2)),
                                          ("crop_margin_range", (0.5, 0.2)),
                                          ("crop_max_upscale", 0.5)])
def test_bad_settings_raise_input_errors(tiny_sampling, field, value):
  with pytest.raises(InputError, match=field):
    dataclasses.replace(tiny_sampling, **{field: value})


def test_unsatisfiable_settings_fail_after_max_attempts(tiny_sampling):
  settings = dataclasses.replace(tiny_sampling, min_object_pixels=10**6, max_attempts=2)
  with pytest.raises(InputError, match="2 attempts"):
    make(settings, 0, False)
