"""Writers of COLMAP models and NeuS/IDR camera files, for the reader tests (the library only
reads these formats). Written from the formats' descriptions, independently of the readers:
quaternions come from scipy, projections are assembled as K [R | t]."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from scipy.spatial import transform

from signerf_jax import files
from signerf_jax.data import colmap_model

COLMAP_MODEL_IDS = {name: model_id for model_id, (name, _) in colmap_model.MODELS_BY_ID.items()}
# OpenGL camera axes (right, up, back) -> OpenCV's (right, down, forward), and back.
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def opencv_world_to_camera(camera_to_world) -> tuple[np.ndarray, np.ndarray]:
  """(R [3, 3], t [3]) with x_camera = R x_world + t in OpenCV axes, of an OpenGL pose."""
  camera_to_world = np.asarray(camera_to_world, np.float64)
  rotation = FLIP_YZ @ camera_to_world[:3, :3].T
  return rotation, -rotation @ camera_to_world[:3, 3]


def colmap_image(image_id: int, camera_id: int, name: str,
                 camera_to_world) -> colmap_model.ColmapImage:
  """A registered image at an OpenGL camera-to-world pose."""
  rotation, translation = opencv_world_to_camera(camera_to_world)
  x, y, z, w = transform.Rotation.from_matrix(rotation).as_quat()
  return colmap_model.ColmapImage(image_id, (w, x, y, z), tuple(translation), camera_id, name)


def write_colmap_model(folder, cameras, images, points, binary: bool) -> None:
  """cameras, images and points3D files in `folder` (`binary`: .bin, else .txt).

  Args:
    cameras: ColmapCameras; images: ColmapImages (each with two 2D points, one of them tied to
      point 1); points: [P, 3] positions, ids 1..P, each seen by the first image.
  """
  folder = Path(folder)
  folder.mkdir(parents=True, exist_ok=True)
  write = _write_binary if binary else _write_text
  write(folder, cameras, images, np.asarray(points, np.float64))


def _write_binary(folder: Path, cameras, images, points: np.ndarray) -> None:
  data = struct.pack("<Q", len(cameras))
  for camera in cameras:
    data += struct.pack("<IiQQ", camera.camera_id, COLMAP_MODEL_IDS[camera.model], camera.width,
                        camera.height)
    data += struct.pack(f"<{len(camera.params)}d", *camera.params)
  (folder / "cameras.bin").write_bytes(data)

  data = struct.pack("<Q", len(images))
  for image in images:
    data += struct.pack("<I7dI", image.image_id, *image.quaternion, *image.translation,
                        image.camera_id)
    data += image.name.encode("utf-8") + b"\0"
    data += struct.pack("<Q", 2) + struct.pack("<ddq", 1.5, 2.5, 1) + struct.pack("<ddq", 3.0,
                                                                                  4.0, -1)
  (folder / "images.bin").write_bytes(data)

  data = struct.pack("<Q", len(points))
  for point_id, position in enumerate(points, start=1):
    data += struct.pack("<Q3d3BdQ", point_id, *position, 200, 100, 50, 0.5, 1)
    data += struct.pack("<II", images[0].image_id, 0)
  (folder / "points3D.bin").write_bytes(data)


def _numbers(values) -> list[str]:
  """Exact text of float values (repr of Python floats round-trips)."""
  return [repr(float(value)) for value in values]


def _write_text(folder: Path, cameras, images, points: np.ndarray) -> None:
  lines = ["# Camera list with one line of data per camera:",
           "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
           f"# Number of cameras: {len(cameras)}"]
  lines += [" ".join([str(camera.camera_id), camera.model, str(camera.width), str(camera.height),
                      *_numbers(camera.params)]) for camera in cameras]
  (folder / "cameras.txt").write_text("\n".join(lines) + "\n")

  lines = ["# Image list with two lines of data per image:",
           "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
           "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
  for index, image in enumerate(images):
    lines.append(" ".join([str(image.image_id), *_numbers(image.quaternion),
                           *_numbers(image.translation), str(image.camera_id), image.name]))
    # COLMAP writes an image without points as an empty line: keep one such.
    lines.append("" if index == 1 else "1.5 2.5 1 3.0 4.0 -1")
  (folder / "images.txt").write_text("\n".join(lines) + "\n")

  lines = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
  lines += [" ".join([str(point_id), *_numbers(position), "200 100 50 0.5",
                      f"{images[0].image_id} 0"])
            for point_id, position in enumerate(points, start=1)]
  (folder / "points3D.txt").write_text("\n".join(lines) + "\n")


def write_images(folder, names, width: int, height: int) -> np.ndarray:
  """Writes a flat grey PNG per name (view k at (k + 1) / 20) and returns them [N, H, W, 3]."""
  images = np.stack([np.full((height, width, 3), (index + 1) / 20, np.float32)
                     for index in range(len(names))])
  for name, image in zip(names, images):
    files.write_image(Path(folder) / name, image)
  return images


def neus_world_mat(camera_to_world, fx, fy, cx, cy, scale: float = 1.0) -> np.ndarray:
  """NeuS's 4x4 world_mat = scale * K [R | t] (bottom row [0, 0, 0, 1]) of an OpenGL camera with
  this project's intrinsics (NeuS puts pixel centres at whole numbers: K's principal point is
  0.5 less)."""
  intrinsics = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
  rotation, translation = opencv_world_to_camera(camera_to_world)
  world_mat = np.eye(4)
  world_mat[:3] = scale * intrinsics @ np.concatenate([rotation, translation[:, None]], 1)
  return world_mat


def neus_scale_mat(centre, radius: float) -> np.ndarray:
  """The similarity mapping NeuS's unit sphere onto the sphere (centre, radius)."""
  scale_mat = np.diag([radius, radius, radius, 1.0])
  scale_mat[:3, 3] = centre
  return scale_mat
