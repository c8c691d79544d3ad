"""Camera paths through a trained scene, for videos of its renders."""

from __future__ import annotations

import numpy as np

from signerf_jax import camera
from signerf_jax.nerf import model as nerf_model


def orbit_cameras(model: nerf_model.NerfModel, reference: camera.Cameras, num_frames: int
                  ) -> camera.Cameras:
  """A camera path through the scene, with the intrinsics of the first reference camera.

  Bounded and unbounded scenes: one turn around the bounds' centre at the reference cameras'
  mean distance and height, about the mean up vector. Forward-facing scenes: a small circle in
  the mean camera's image plane, looking at the scene centre.
  """
  positions = np.asarray(reference.positions)
  centre = np.mean(np.asarray(model.scene.bounds), axis=0)
  up = np.mean(np.asarray(reference.camera_to_world)[:, :, 1], axis=0)
  up = up / np.linalg.norm(up)
  angles = np.linspace(0.0, 2.0 * np.pi, num_frames, endpoint=False)
  if model.scene.kind == "forward_facing":
    mean_pose = np.asarray(reference.camera_to_world).mean(axis=0)
    right, camera_up = mean_pose[:, 0], mean_pose[:, 1]
    radius = 0.5 * np.std(positions @ right) + 0.5 * np.std(positions @ camera_up)
    eyes = (positions.mean(axis=0) + radius * (np.cos(angles)[:, None] * right +
                                               np.sin(angles)[:, None] * camera_up))
    target = positions.mean(axis=0) - mean_pose[:, 2] * np.linalg.norm(
        centre - positions.mean(axis=0))
  else:
    offsets = positions - centre
    height = np.mean(offsets @ up)
    radius = np.mean(np.linalg.norm(offsets - np.outer(offsets @ up, up), axis=-1))
    first = offsets[0] - (offsets[0] @ up) * up
    first = first / max(np.linalg.norm(first), 1e-9)
    second = np.cross(up, first)
    eyes = centre + height * up + radius * (np.cos(angles)[:, None] * first +
                                            np.sin(angles)[:, None] * second)
    target = centre
  camera_to_world = camera.look_at(eyes.astype(np.float32),
                                   np.broadcast_to(target, eyes.shape).astype(np.float32),
                                   up.astype(np.float32))
  first_camera = reference.take([0])
  return camera.Cameras.create(np.asarray(camera_to_world), first_camera.fx[0], first_camera.fy[0],
                               first_camera.cx[0], first_camera.cy[0], width=reference.width,
                               height=reference.height)
