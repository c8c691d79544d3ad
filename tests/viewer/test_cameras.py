"""The viewer's cameras: a dataset camera shown in the browser and rendered back is the same
camera (OpenCV axes in viser, OpenGL axes here)."""

import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.viewer.cameras import ViewPose, cameras_for_pose, pose_of_camera


def dataset_cameras(width=48, height=32):
  eyes = np.array([[2.0, -1.0, 1.0], [0.0, 0.0, 3.0], [-1.0, 2.0, -0.5]], np.float32)
  camera_to_world = np.asarray(camera.look_at(eyes, np.zeros((3, 3), np.float32)))
  return camera.Cameras.create(camera_to_world, fx=40.0, width=width, height=height)


@pytest.mark.parametrize("index", [0, 1, 2])
def test_a_dataset_camera_shown_in_the_viewer_renders_as_itself(index):
  cameras = dataset_cameras()
  pose = pose_of_camera(cameras, index)
  assert pose.aspect == pytest.approx(48 / 32)
  back = cameras_for_pose(pose, 32)
  assert (back.width, back.height) == (48, 32)
  np.testing.assert_allclose(back.camera_to_world[0], cameras.camera_to_world[index], atol=1e-5)
  np.testing.assert_allclose(back.fy[0], 40.0, rtol=1e-5)
  ours, theirs = camera.image_rays(back, 0), camera.image_rays(cameras, index)
  np.testing.assert_allclose(ours.directions, theirs.directions, atol=1e-5)


def test_the_viewer_looks_along_opencv_z_with_y_down():
  # viser's identity rotation looks down the world's +z with +y down the image.
  pose = ViewPose((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), np.pi / 2, 2.0)
  cameras = cameras_for_pose(pose, 64)
  assert cameras.width == 128
  np.testing.assert_allclose(cameras.forward[0], [0.0, 0.0, 1.0], atol=1e-6)
  rays = camera.image_rays(cameras, 0)
  assert float(rays.directions[-1, 64, 1]) > 0  # The bottom row looks towards +y.
  assert float(rays.directions[32, -1, 0]) > 0  # The right column towards +x.
  np.testing.assert_allclose(cameras.fy[0], 32.0, rtol=1e-6)  # 90 degrees over 64 px.
