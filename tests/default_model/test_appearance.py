"""Appearances: patterns live on the object (view-consistent), and colours survive shading."""

import colorsys
import dataclasses

import numpy as np
import pytest
import trimesh

from signerf_jax.data import synthetic, synthetic_render
from signerf_jax.default_model import appearance, captions, objects, samples, scenes
from signerf_jax.geometry import reference_cameras
from signerf_jax.metrics import colors


@pytest.mark.parametrize("kind_name", ["cube", "torus"])
@pytest.mark.parametrize("pattern", ["striped", "checkered", "spotted"])
def test_a_surface_point_has_one_albedo_from_every_camera(tiny_sampling, kind_name, pattern):
  rng = np.random.default_rng(1)
  scene, _ = scenes.random_scene(rng, tiny_sampling, captions.Attributes("ball", "red", "plain"))
  kind = next(kind for kind in tiny_sampling.catalogue() if kind.name == kind_name)
  look = appearance.random_appearance(rng, "red", pattern)
  placement = objects.Placement(center=np.array([0.1, -0.2]), footprint_radius=0.3, yaw=0.7,
                                height_stretch=1.1)
  target = objects.scene_object(kind, placement, look, object_id=1)
  scene = dataclasses.replace(scene, objects=(target,))  # Nothing else occludes the object.
  center, _ = reference_cameras.selection_sphere(target.world_bounds())
  # Rays from a first camera towards points around the object find surface points P.
  first_eye = center + np.array([1.5, -0.4, 1.0])
  aims = center + rng.uniform(-0.15, 0.15, (400, 3))
  directions = aims - first_eye
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  hits = synthetic_render.cast_rays(scene, np.broadcast_to(first_eye, aims.shape), directions)
  on_object = hits.object_ids == 1
  points = first_eye + hits.t[on_object, None] * directions[on_object]
  # Object coordinates by the module's definition: base centre at 0, no yaw, footprint radius 1.
  base = np.array([0.1, -0.2, synthetic.GROUND_HEIGHT])
  unrotate = trimesh.transformations.rotation_matrix(-0.7, (0, 0, 1))[:3, :3]
  expected = look.albedo((points - base) @ unrotate.T / 0.3)
  np.testing.assert_allclose(hits.albedo[on_object], expected, atol=1e-9)
  # A second camera elsewhere sees the same points (those it sees) with the same albedo.
  second_eye = center + np.array([-1.2, 1.3, 0.8])
  back = points - second_eye
  distance = np.linalg.norm(back, axis=-1)
  second = synthetic_render.cast_rays(scene, np.broadcast_to(second_eye, back.shape),
                                      back / distance[:, None])
  visible = (second.object_ids == 1) & (np.abs(second.t - distance) < 1e-6)
  assert visible.sum() > 20
  np.testing.assert_allclose(second.albedo[visible], hits.albedo[on_object][visible], atol=1e-9)
  # The pattern is not uniform: the test would notice a pattern in the wrong frame.
  assert np.ptp(hits.albedo[on_object][:, 0]) > 0.2


@pytest.mark.parametrize("pattern, fraction", [("plain", 0.0), ("striped", 0.4),
                                               ("checkered", 0.5), ("spotted", 0.2)])
def test_accent_covers_a_minority_of_the_surface(pattern, fraction):
  rng = np.random.default_rng(0)
  directions = rng.normal(size=(20000, 3))
  points = 1.3 * directions / np.linalg.norm(directions, axis=-1, keepdims=True)
  weights = [appearance.random_appearance(rng, "blue", pattern).accent_weight(points).mean()
             for _ in range(8)]
  assert np.mean(weights) == pytest.approx(fraction, abs=0.07)


def test_accent_keeps_the_base_hue():
  for name, (base, accent) in colors.PALETTE.items():
    if name in colors.ACHROMATIC_COLORS:
      assert np.ptp(base) < 0.03 and np.ptp(accent) < 0.03
      continue
    assert colorsys.rgb_to_hsv(*accent)[0] == pytest.approx(colorsys.rgb_to_hsv(*base)[0], abs=0.01)


def test_dominant_color_is_recovered_from_shaded_renders(tiny_sampling):
  settings = dataclasses.replace(tiny_sampling, reference_view_probability=1.0)
  rng = np.random.default_rng(2)
  for color in colors.COLORS:
    for pattern in appearance.PATTERNS:
      sample = samples.make_sample(rng, settings, captions.CaptionSettings(), sheet=False,
                                   attributes=captions.Attributes("cube", color, pattern))
      pixels = sample.views["rgb"][0][sample.views["silhouette"][0] > 0] / 255.0
      assert colors.dominant_color(pixels) == color, (color, pattern)
