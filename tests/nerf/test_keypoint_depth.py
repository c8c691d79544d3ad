"""Keypoint depths: triangulated keypoints of views of a textured plane lie on the plane, at the
distance the cameras see it; textureless views give none; sparse captures of whole scenes
train with them (when the capture chooses them: tests/nerf/test_capture_choices.py)."""

import cv2
import numpy as np

from signerf_jax import camera
from signerf_jax.data.dataset import Dataset
from signerf_jax.nerf import capture_choices, keypoint_depth, train, training_run


def plane_views(texture_seed: int | None, size: int = 160):
  """Views of the plane z = 0 textured with blurred noise (or uniform grey with None) from
  cameras 2 units above it, 0.4 apart, looking down and a little forward."""
  eyes = [(-0.4, -1.0, 2.0), (0.0, -1.0, 2.0), (0.4, -1.0, 2.0), (0.4, -0.6, 2.1)]
  poses = np.stack([np.asarray(camera.look_at(np.array(eye), np.array([eye[0], 0.0, 0.0]),
                                              up=(0.0, 1.0, 0.0))) for eye in eyes])
  cameras = camera.Cameras.create(poses, 150.0, width=size, height=size,
                                  distortion=(-0.05, 0.01, 0.0, 0.0))
  texture = np.full((512, 512), 0.5, np.float32)
  if texture_seed is not None:
    texture = np.random.default_rng(texture_seed).random((512, 512)).astype(np.float32)
    texture = cv2.GaussianBlur(texture, (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
  images = []
  for index in range(len(eyes)):
    rays = camera.image_rays(cameras, index)
    origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
    hit = origins - directions * (origins[..., 2:] / directions[..., 2:])
    # The plane's [-2, 2]^2 spans the texture.
    u = ((hit[..., 0] + 2.0) / 4.0 * 512 - 0.5).astype(np.float32)
    v = ((hit[..., 1] + 2.0) / 4.0 * 512 - 0.5).astype(np.float32)
    gray = cv2.remap(texture, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    images.append(np.repeat(gray[..., None], 3, axis=-1))
  return np.stack(images), cameras


def test_triangulated_keypoints_lie_on_the_plane_at_the_seen_distance():
  images, cameras = plane_views(texture_seed=0)
  depths = keypoint_depth.triangulate(images, cameras)
  assert depths.count >= 100 and set(np.asarray(depths.camera_indices)) == {0, 1, 2, 3}
  rays = camera.pixel_rays(cameras, depths.camera_indices, depths.pixels[:, 0],
                           depths.pixels[:, 1])
  origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
  seen = -origins[:, 2] / directions[:, 2]  # where the pixel's own ray meets the plane
  relative = np.abs(np.asarray(depths.distances) - seen) / seen
  assert np.percentile(relative, 95) < 0.02 and np.max(relative) < 0.1


def test_textureless_views_give_no_keypoints():
  images, cameras = plane_views(texture_seed=None)
  depths = keypoint_depth.triangulate(images, cameras)
  assert depths.count == 0 and depths.pixels.shape == (0, 2)


def test_a_sparse_capture_with_a_background_trains_on_its_keypoints():
  images, cameras = plane_views(texture_seed=1)
  dataset = Dataset(images=images, cameras=cameras,
                    image_names=tuple(f"view_{index}.png" for index in range(len(images))),
                    scene_bounds=np.array([[-1, -1, -0.5], [1, 1, 0.5]], np.float32),
                    scene_kind="unbounded", near=0.1, far=10.0)
  trainer = training_run.make_trainer(dataset)
  assert trainer.config.keypoint_depth_weight == capture_choices.SPARSE_KEYPOINT_DEPTH_WEIGHT
  assert trainer.data.keypoints is not None and trainer.data.keypoints.count >= 100
  off = training_run.make_trainer(dataset, config=train.TrainConfig(keypoint_depth_weight=0.0))
  assert off.data.keypoints is None
