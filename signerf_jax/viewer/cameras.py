"""Cameras between the browser viewer and the project.

viser's cameras (the browser's view and the frustums it draws) follow OpenCV's axes (x right,
y down, z forward) with a vertical field of view; `camera.Cameras` follow OpenGL's (x right,
y up, z backwards) with focal lengths in pixels.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from viser import transforms

from signerf_jax import camera as camera_lib

# Flips y and z: OpenCV camera axes <-> OpenGL camera axes (its own inverse).
OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0])


@dataclasses.dataclass(frozen=True)
class ViewPose:
  """A viewer camera.

  Attributes:
    wxyz: [4] unit quaternion, camera (OpenCV axes) to world rotation.
    position: [3] camera centre, world units.
    vertical_fov: vertical field of view, radians.
    aspect: width / height.
  """

  wxyz: tuple[float, float, float, float]
  position: tuple[float, float, float]
  vertical_fov: float
  aspect: float


def cameras_for_pose(pose: ViewPose, height: int) -> camera_lib.Cameras:
  """One ideal pinhole camera [1] seeing what the viewer's `pose` sees, `height` pixels high
  (and round(height * aspect) wide)."""
  width = max(1, round(height * pose.aspect))
  rotation = transforms.SO3(np.asarray(pose.wxyz, np.float64)).as_matrix() @ OPENCV_FROM_OPENGL
  camera_to_world = np.concatenate([rotation, np.asarray(pose.position, np.float64)[:, None]], 1)
  focal = 0.5 * height / np.tan(0.5 * pose.vertical_fov)
  return camera_lib.Cameras.create(camera_to_world[None], focal, width=width, height=height)


def pose_of_camera(cameras: camera_lib.Cameras, index: int) -> ViewPose:
  """The viewer pose of camera `index` (its vertical field of view from fy and the height; the
  principal point and lens distortion are not shown)."""
  camera_to_world = np.asarray(cameras.camera_to_world[index], np.float64)
  rotation = camera_to_world[:, :3] @ OPENCV_FROM_OPENGL
  wxyz = transforms.SO3.from_matrix(rotation).wxyz
  vertical_fov = 2.0 * np.arctan(0.5 * cameras.height / float(cameras.fy[index]))
  return ViewPose(tuple(map(float, wxyz)), tuple(map(float, camera_to_world[:, 3])),
                  float(vertical_fov), cameras.width / cameras.height)
