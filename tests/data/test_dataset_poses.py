import numpy as np
import pytest

from signerf_jax import camera
from signerf_jax.data import poses
from signerf_jax.errors import InputError


@pytest.mark.parametrize("source, target", [
    ([0, 0, 1], [0, 1, 0]), ([1, 2, 3], [1, 2, 3]), ([0, 0, 1], [0, 0, -1]),
    ([1, 0, 0], [-1, 0, 0]), ([0.3, -0.2, 0.9], [-0.5, 0.1, 0.2])])
def test_rotation_between_is_proper_and_maps_source_to_target(source, target):
  rotation = poses.rotation_between(source, target)
  np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
  assert np.linalg.det(rotation) == pytest.approx(1.0)
  np.testing.assert_allclose(rotation @ source / np.linalg.norm(source),
                             np.divide(target, np.linalg.norm(target)), atol=1e-12)


def test_llff_axes_become_opengl_axes():
  # An LLFF camera whose columns are [down, right, backwards] = [-y, x, z] is the identity pose.
  llff = np.array([[0.0, 1, 0, 5], [-1, 0, 0, 6], [0, 0, 1, 7]])
  np.testing.assert_array_equal(poses.llff_to_opengl(llff), [[1, 0, 0, 5], [0, 1, 0, 6],
                                                             [0, 0, 1, 7]])


def test_similarities_map_poses_rigidly_and_fit_boxes():
  matrix = poses.unit_box_similarity([-2.0, 0.0, 1.0], [2.0, 1.0, 3.0])
  np.testing.assert_allclose(poses.transform_points(matrix, [[-2.0, 0.0, 1.0], [2.0, 1.0, 3.0]]),
                             [[-1, -0.25, -0.5], [1, 0.25, 0.5]])
  assert poses.similarity_scale(matrix) == pytest.approx(0.5)
  rotated = poses.similarity(3.0, poses.rotation_between([1, 0, 0], [0, 1, 1]), [1, 2, 3])
  pose = np.asarray(camera.look_at(np.array([1.0, 2, 3]), np.zeros(3)), np.float64)
  mapped = poses.transform_poses(rotated, pose[None])[0]
  np.testing.assert_allclose(mapped[:, :3].T @ mapped[:, :3], np.eye(3), atol=1e-6)
  np.testing.assert_allclose(mapped[:, 3], poses.transform_points(rotated, pose[:, 3]))


def test_near_far_cover_the_box_from_inside_and_outside():
  bounds = np.array([[-1.0, -1, -1], [1, 1, 1]])
  eyes = np.array([[0.0, 0, 0.5], [0.0, 0, 4.0]], np.float32)
  cameras = camera.Cameras.create(camera.look_at(eyes, np.array([0.0, 1, 0], np.float32)),
                                  fx=10.0, width=8, height=8)
  near, far = poses.near_far_for_box(cameras, *bounds)
  assert far == pytest.approx(np.linalg.norm([1, 1, 5]))
  assert near == pytest.approx(1e-3 * far)  # the first camera is inside the box
  near, _ = poses.near_far_for_box(cameras.take([1]), *bounds)
  assert near == pytest.approx(3.0)


@pytest.mark.parametrize("focal", [0, -1.0, float("nan"), float("inf"), "7", None])
def test_focal_lengths_must_be_finite_and_positive(focal):
  assert poses.check_focal_length(np.float32(7), "file.json", "fl_x") == 7.0
  with pytest.raises(InputError, match="file.json: fl_x"):
    poses.check_focal_length(focal, "file.json", "fl_x")
