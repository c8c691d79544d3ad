"""NeuS / IDR captures written by `capture_writers` read back in the world_mat frame, and every
kind of bad camera file is an InputError naming the file and the key."""

import numpy as np
import pytest
from capture_writers import neus_scale_mat, neus_world_mat, write_images

from signerf_jax import camera, files
from signerf_jax.data import detect_format, load_dataset, neus, poses
from signerf_jax.errors import InputError

WIDTH, HEIGHT, COUNT = 10, 8, 5
TARGET = np.array([1.0, -2.0, 0.5])
SPHERE_CENTRE, SPHERE_RADIUS = np.array([1.1, -1.9, 0.45]), 0.8
# Per-view intrinsics (fx, fy, cx, cy) in this project's convention, and world_mat's arbitrary
# projective scale (NeuS's files are K [R | t] up to scale, sign included).
INTRINSICS = [(9.0 + index, 9.5 + index, 5.2 - 0.1 * index, 3.9 + 0.1 * index)
              for index in range(COUNT)]
PROJECTIVE_SCALES = [1.0, 2.5, -1.0, 0.01, -40.0]


def ring_poses():
  angles = np.linspace(0, 2 * np.pi, COUNT, endpoint=False)
  eyes = TARGET + np.stack([4 * np.cos(angles), 4 * np.sin(angles), 1.5 + 0 * angles], -1)
  return np.asarray(camera.look_at(eyes.astype(np.float32), TARGET.astype(np.float32)),
                    np.float64)


def write_capture(root, camera_name="cameras_sphere.npz", image_folder="image", masks=True,
                  **replaced):
  """A NeuS capture of COUNT views; `replaced` overrides entries of the npz (None drops one).

  Returns:
    (images [N, H, W, 3], masks [N, H, W] in {0, 1}, OpenGL camera-to-world [N, 3, 4]).
  """
  camera_to_world = ring_poses()
  arrays = {}
  for index, (pose, intrinsics, scale) in enumerate(zip(camera_to_world, INTRINSICS,
                                                        PROJECTIVE_SCALES)):
    arrays[f"world_mat_{index}"] = neus_world_mat(pose, *intrinsics, scale=scale)
    arrays[f"scale_mat_{index}"] = neus_scale_mat(SPHERE_CENTRE, SPHERE_RADIUS)
  arrays.update(replaced)
  np.savez(root / camera_name, **{key: value for key, value in arrays.items()
                                  if value is not None})
  names = [f"{index:03d}.png" for index in range(COUNT)]
  images = write_images(root / image_folder, names, WIDTH, HEIGHT)
  silhouettes = np.zeros((COUNT, HEIGHT, WIDTH), np.float32)
  silhouettes[:, 2:6, 3:7] = 1.0
  if masks:
    for name, silhouette in zip(names, silhouettes):
      # NeuS's masks are RGB, 0 or 255.
      files.write_image(root / "mask" / name, np.repeat(silhouette[..., None], 3, -1))
  return images, silhouettes, camera_to_world


@pytest.mark.parametrize("camera_name, image_folder", [("cameras_sphere.npz", "image"),
                                                       ("cameras.npz", "images")])
def test_cameras_images_masks_and_object_sphere_read_back_in_the_world_mat_frame(
    tmp_path, camera_name, image_folder):
  images, silhouettes, camera_to_world = write_capture(tmp_path, camera_name, image_folder)
  assert detect_format(tmp_path) == "neus"
  dataset = load_dataset(tmp_path, split="all")

  assert dataset.image_names == tuple(f"{image_folder}/{index:03d}.png" for index in range(COUNT))
  np.testing.assert_allclose(dataset.images, images, atol=0.5 / 255)
  np.testing.assert_array_equal(dataset.extras["object_masks"], silhouettes.astype(np.int32))
  cameras = dataset.cameras
  source_from_world = np.linalg.inv(np.asarray(dataset.world_from_source, np.float64))
  np.testing.assert_allclose(poses.transform_poses(source_from_world, cameras.camera_to_world),
                             camera_to_world, atol=2e-5)
  np.testing.assert_allclose(np.stack([cameras.fx, cameras.fy, cameras.cx, cameras.cy], -1),
                             INTRINSICS, rtol=1e-5)
  assert not np.any(cameras.distortion) and not cameras.fisheye

  capture = neus.read_capture(tmp_path)
  centre, radius = capture.object_sphere
  np.testing.assert_allclose(centre, SPHERE_CENTRE, atol=1e-12)
  assert radius == pytest.approx(SPHERE_RADIUS)


def test_without_masks_or_scale_mats_there_are_no_object_masks_or_sphere(tmp_path):
  write_capture(tmp_path, masks=False, **{f"scale_mat_{index}": None for index in range(COUNT)})
  assert "object_masks" not in load_dataset(tmp_path, split="all").extras
  assert neus.read_capture(tmp_path).object_sphere is None


def rotated_projection():
  """world_mat_2 with its rotation scaled along one axis: not K [R | t] for any R."""
  matrix = neus_world_mat(ring_poses()[2], *INTRINSICS[2])
  matrix[:3, :3] = matrix[:3, :3] @ np.diag([1.0, 1.0, 1e-12])
  return matrix


def skewed_projection():
  matrix = neus_world_mat(ring_poses()[2], *INTRINSICS[2])
  skew = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
  matrix[:3] = skew @ matrix[:3]
  return matrix


def sheared_scale_mat():
  scale_mat = neus_scale_mat(SPHERE_CENTRE, SPHERE_RADIUS)
  scale_mat[0, 1] = 0.2
  return scale_mat


BAD_CAMERA_FILES = {
    "missing world_mat": ({"world_mat_3": None}, "world_mat_3", "missing"),
    "world_mat without an image": ({"world_mat_5": np.eye(4)}, "world_mat_5", "has no image"),
    "world_mat 3x3": ({"world_mat_1": np.eye(3)}, "world_mat_1", "finite 3x4 or 4x4"),
    "world_mat NaN": ({"world_mat_4": np.full((4, 4), np.nan)}, "world_mat_4", "finite"),
    "world_mat bad last row": ({"world_mat_0": np.ones((4, 4))}, "world_mat_0", "last row"),
    "singular world_mat": ({"world_mat_2": rotated_projection()}, "world_mat_2", "singular"),
    "skewed world_mat": ({"world_mat_2": skewed_projection()}, "world_mat_2", "skew"),
    "scale_mat not a similarity": ({f"scale_mat_{index}": sheared_scale_mat()
                                    for index in range(COUNT)}, "scale_mat_0", "similarity"),
    "scale_mats differ": ({"scale_mat_3": neus_scale_mat(SPHERE_CENTRE, 2.0)}, "scale_mat_3",
                          "differs from scale_mat_0"),
}


@pytest.mark.parametrize("case", BAD_CAMERA_FILES)
def test_bad_camera_files_name_the_file_and_the_key(tmp_path, case):
  replaced, key, message = BAD_CAMERA_FILES[case]
  write_capture(tmp_path, **replaced)
  with pytest.raises(InputError, match=message) as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(tmp_path / "cameras_sphere.npz")
  assert error.value.field == key


def test_mask_and_image_counts_must_match_and_the_archive_must_be_readable(tmp_path):
  write_capture(tmp_path)
  (tmp_path / "mask" / "002.png").unlink()
  with pytest.raises(InputError, match="holds 4 masks but there are 5 images") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(tmp_path / "mask")

  (tmp_path / "cameras_sphere.npz").write_bytes(b"PK\x03\x04 not really a zip")
  with pytest.raises(InputError, match="not a readable .npz archive") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(tmp_path / "cameras_sphere.npz")


def cameras_of(root):
  """(camera-to-world [N, 3, 4], intrinsics [N, 4]) of a capture, in the world_mat frame."""
  cameras = neus.read_capture(root).cameras
  return (np.asarray(cameras.camera_to_world, np.float64),
          np.stack([cameras.fx, cameras.fy, cameras.cx, cameras.cy], -1))


@pytest.mark.parametrize("scale", [1e300, 1e-300, -1e300])
@pytest.mark.parametrize("whole", [False, True], ids=["projection", "whole_4x4"])
def test_a_world_mat_at_any_finite_scale_reads_the_same_cameras(tmp_path, scale, whole):
  # A projection matters only up to scale; 1e300 overflowed the determinant to inf (and 1e-300
  # underflowed it to 0), which was taken for a singular matrix.
  (tmp_path / "plain").mkdir()
  (tmp_path / "scaled").mkdir()
  write_capture(tmp_path / "plain")
  expected = cameras_of(tmp_path / "plain")
  scaled = {}
  for index, (pose, intrinsics) in enumerate(zip(ring_poses(), INTRINSICS)):
    matrix = neus_world_mat(pose, *intrinsics, scale=scale)
    if whole:
      matrix[3, 3] = scale  # The whole homogeneous 4x4 scaled: still the same map.
    scaled[f"world_mat_{index}"] = matrix
  write_capture(tmp_path / "scaled", **scaled)
  actual = cameras_of(tmp_path / "scaled")
  np.testing.assert_allclose(actual[0], expected[0], atol=1e-9)
  np.testing.assert_allclose(actual[1], expected[1], rtol=1e-9)


def test_a_scale_mat_at_a_huge_scale_gives_its_sphere(tmp_path):
  scale_mat = neus_scale_mat(SPHERE_CENTRE, 1e300)
  write_capture(tmp_path, **{f"scale_mat_{index}": scale_mat for index in range(COUNT)})
  centre, radius = neus.read_capture(tmp_path).object_sphere
  np.testing.assert_array_equal(centre, SPHERE_CENTRE)
  assert radius == pytest.approx(1e300)


HUGE_BAD_WORLD_MATS = {
    "singular at 1e300": (rotated_projection() * 1e300, "singular"),
    "rank 1 at 1e300": (np.outer([1.0, 2.0, 3.0, 0.0], [1.0, 1.0, 1.0, 1.0]) * 1e300 + np.diag(
        [0.0, 0.0, 0.0, 1.0]), "singular"),
    "zeros": (np.diag([0.0, 0.0, 0.0, 1.0]), "all zeros"),
    "infinite at 1e300": (np.where(np.eye(3, 4) > 0, np.inf, 1e300), "finite"),
    "complex": (neus_world_mat(ring_poses()[2], *INTRINSICS[2]) + 1e-3j, "real numbers, got "
                "dtype complex128"),
    "text": (neus_world_mat(ring_poses()[2], *INTRINSICS[2]).astype(str), "real numbers"),
    "last row zero": (np.zeros((4, 4)), "last row"),
}


@pytest.mark.parametrize("case", HUGE_BAD_WORLD_MATS)
def test_a_singular_non_finite_or_non_real_world_mat_names_the_file_and_the_key(tmp_path, case):
  matrix, message = HUGE_BAD_WORLD_MATS[case]
  write_capture(tmp_path, world_mat_2=matrix)
  with pytest.raises(InputError, match=message) as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(tmp_path / "cameras_sphere.npz")
  assert error.value.field == "world_mat_2"
