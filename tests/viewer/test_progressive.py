"""Progressive rendering: coarse first, the same pixels as rendering the camera directly,
abandoned as soon as a newer view is asked for, and no recompilation for a new view."""

import dataclasses
import threading

import jax
import numpy as np
import pytest

from analytic_scene import sphere_dataset
from signerf_jax.nerf import capacity, evaluate, render, scene_info
from signerf_jax.nerf import model as nerf_model
from signerf_jax.viewer import progressive
from signerf_jax.viewer.cameras import ViewPose, cameras_for_pose

from small_nerf import count_compilations

pytestmark = pytest.mark.slow



@pytest.fixture(scope="module")
def trained(viewed_run):
  return evaluate.load_run(viewed_run[0])


def test_frames_come_coarse_first_with_the_pixels_of_a_direct_render(trained):
  pose = ViewPose((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -2.5), np.pi / 3, 1.5)
  frames = list(progressive.render_progressively(trained.model, trained.variables, pose,
                                                 lambda: True, heights=(8, 24), chunk_size=128))
  assert [frame.height for frame in frames] == [8, 24]
  assert frames[1].rgb.shape == (24, 36, 3) and frames[1].depth.shape == (24, 36)
  assert frames[0].seconds <= frames[1].seconds
  # The viewer renders one ray through each pixel's centre, whatever the model's pixel_samples.
  direct = render.render_cameras(trained.model, trained.variables, cameras_for_pose(pose, 24),
                                 supersampling=1)
  np.testing.assert_allclose(frames[1].rgb, direct["rgb"][0], atol=1e-6)
  np.testing.assert_allclose(frames[1].depth, direct["depth"][0], atol=1e-5)


def test_frames_before_the_finest_take_a_third_of_the_field_samples():
  dataset = dataclasses.replace(sphere_dataset(), scene_kind="unbounded", background_color=None)
  scene = scene_info.SceneInfo.from_dataset(dataset)
  model = nerf_model.NerfModel(scene, dataclasses.replace(
      capacity.derive_capacity(scene), proposal_samples=(16,), samples_per_ray=12, mlp_width=16))
  variables = nerf_model.init_variables(model, jax.random.key(0))
  pose = ViewPose((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -2.5), np.pi / 3, 1.0)
  frames = list(progressive.render_progressively(model, variables, pose, lambda: True,
                                                 heights=(8, 16), chunk_size=128))

  def direct(fraction, height):
    rendering = dataclasses.replace(model, capacity=dataclasses.replace(
        model.capacity, render_sample_fraction=fraction))
    rendered = render.render_cameras(rendering, variables, cameras_for_pose(pose, height))
    return rendered["rgb"][0], rendered["depth"][0]

  assert model.capacity.sample_counts(training=False) == ((16,), 12)
  for frame, expected in [(frames[0], direct(1 / 3, 8)),  # 16 > 4 samples a ray.
                          (frames[1], direct(1.0, 16))]:  # As the model says: 16 > 12.
    np.testing.assert_allclose(frame.rgb, expected[0], atol=1e-6)
    np.testing.assert_allclose(frame.depth, expected[1], rtol=1e-5)
  assert np.abs(frames[0].depth - direct(1.0, 8)[1]).max() > 1e-3


def test_a_frame_is_abandoned_between_chunks_when_the_view_changes(trained):
  checks = []

  def is_current():
    checks.append(None)
    return len(checks) < 3  # The first frame's one chunk, the second's first chunk, then stop.

  pose = ViewPose((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -2.5), np.pi / 3, 1.0)
  frames = list(progressive.render_progressively(trained.model, trained.variables, pose,
                                                 is_current, heights=(8, 32), chunk_size=64))
  assert [frame.height for frame in frames] == [8]
  assert len(checks) == 3  # 32 x 32 px is 16 chunks: 14 were never rendered.


def test_a_new_view_renders_without_compiling_again(trained):
  poses = [ViewPose((1.0, 0.0, 0.0, 0.0), (x, 0.0, -2.5), np.pi / 3, 1.0) for x in (0.0, 0.3)]
  list(progressive.render_progressively(trained.model, trained.variables, poses[0],
                                        lambda: True, heights=(8, 16), chunk_size=64))
  with count_compilations() as compiled:
    list(progressive.render_progressively(trained.model, trained.variables, poses[1],
                                          lambda: True, heights=(8, 16), chunk_size=64))
  assert not compiled


def test_the_renderer_shows_only_the_newest_view():
  """The thread logic alone: a frame of an older view finished after a newer request is not
  shown, and the newest view is rendered to its finest frame."""
  shown, release = [], threading.Event()
  everything_shown = threading.Event()

  def frames(pose, is_current):
    for height in (1, 2):
      if pose == "old" and height == 2:
        release.wait()
      yield progressive.Frame(np.full((height, 1, 3), 0.5), np.zeros((height, 1)), 0.0)
      if pose == "new" and height == 2:
        everything_shown.set()

  def show(frame):
    shown.append((current["pose"], frame.height))

  current = {"pose": "old"}
  renderer = progressive.ProgressiveRenderer(frames, show)
  try:
    renderer.request("old")
    while not shown:
      threading.Event().wait(0.01)
    current["pose"] = "new"
    renderer.request("new")
    release.set()
    assert everything_shown.wait(10.0)
  finally:
    renderer.close()
  assert shown == [("old", 1), ("new", 1), ("new", 2)]
