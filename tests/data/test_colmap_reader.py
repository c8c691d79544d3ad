"""COLMAP models written by `capture_writers` (binary and text) read back exactly, and every kind
of bad model is an InputError naming the file and the record."""

import numpy as np
import pytest
from capture_writers import colmap_image, write_colmap_model, write_images

from signerf_jax import camera
from signerf_jax.data import colmap, colmap_model, detect_format, load_dataset, poses
from signerf_jax.errors import InputError

WIDTH, HEIGHT = 8, 6
# model: (COLMAP parameters, expected (fx, fy, cx, cy), expected OpenCV coefficients).
PERSPECTIVE_MODELS = {
    "SIMPLE_PINHOLE": ((7.0, 4.1, 2.9), (7.0, 7.0, 4.1, 2.9), ()),
    "PINHOLE": ((7.0, 7.3, 4.2, 3.1), (7.0, 7.3, 4.2, 3.1), ()),
    "SIMPLE_RADIAL": ((6.5, 3.9, 3.05, -0.08), (6.5, 6.5, 3.9, 3.05), (-0.08,)),
    "RADIAL": ((6.8, 4.05, 2.95, -0.1, 0.02), (6.8, 6.8, 4.05, 2.95), (-0.1, 0.02)),
    "OPENCV": ((7.1, 6.9, 4.0, 3.0, -0.1, 0.02, 0.001, -0.002), (7.1, 6.9, 4.0, 3.0),
               (-0.1, 0.02, 0.001, -0.002)),
    "FULL_OPENCV": ((7.1, 6.9, 4.0, 3.0, -0.1, 0.02, 0.001, -0.002, 0.003, 0.05, -0.01, 0.002),
                    (7.1, 6.9, 4.0, 3.0), (-0.1, 0.02, 0.001, -0.002, 0.003, 0.05, -0.01, 0.002)),
}
FISHEYE_MODELS = {
    "OPENCV_FISHEYE": ((4.0, 4.2, 4.0, 3.0, 0.05, -0.01, 0.002, -0.0005), (4.0, 4.2, 4.0, 3.0),
                       (0.05, -0.01, 0.002, -0.0005)),
    "SIMPLE_RADIAL_FISHEYE": ((4.1, 4.0, 3.0, 0.03), (4.1, 4.1, 4.0, 3.0), (0.03,)),
    "RADIAL_FISHEYE": ((4.1, 4.0, 3.0, 0.03, -0.004), (4.1, 4.1, 4.0, 3.0), (0.03, -0.004)),
    "SIMPLE_FISHEYE": ((4.1, 4.0, 3.0), (4.1, 4.1, 4.0, 3.0), ()),
    "FISHEYE": ((4.1, 4.3, 4.0, 3.0), (4.1, 4.3, 4.0, 3.0), ()),
}
LENS_KINDS = {"perspective": PERSPECTIVE_MODELS, "fisheye": FISHEYE_MODELS}
# Unsupported models with parameter lists of their lengths.
UNSUPPORTED = {"FOV": 5, "THIN_PRISM_FISHEYE": 12, "RAD_TAN_THIN_PRISM_FISHEYE": 16,
               "SIMPLE_DIVISION": 4, "DIVISION": 5, "EUCM": 6, "EQUIRECTANGULAR": 2}
POINTS = np.array([[0.2, -0.1, 0.3], [0.5, 0.25, -0.125], [-0.3, 0.4, 0.1], [0.0, 0.0, 0.7]])


def ring_poses(count):
  """OpenGL camera-to-world of `count` cameras on a ring, looking at a point off the origin."""
  angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
  target = np.array([0.2, -0.1, 0.3])
  eyes = target + np.stack([3 * np.cos(angles), 3 * np.sin(angles), np.full(count, 0.8)], -1)
  return np.asarray(camera.look_at(eyes.astype(np.float32), target.astype(np.float32)),
                    np.float64)


def make_rig(models):
  """One camera and one image per model, camera ids 11.., image ids counting down while the
  names count up (so id order is not name order), written in a shuffled order."""
  poses_ = ring_poses(len(models))
  cameras = [colmap_model.ColmapCamera(11 + index, model, WIDTH, HEIGHT, params)
             for index, (model, (params, _, _)) in enumerate(models.items())]
  images = [colmap_image(len(models) - index, 11 + index, f"view_{index:02d}.png", pose)
            for index, pose in enumerate(poses_)]
  order = np.random.default_rng(0).permutation(len(images))
  return cameras, [images[index] for index in order], poses_


def write_rig(root, models=PERSPECTIVE_MODELS, binary=True, folder="sparse/0"):
  cameras, images, camera_to_world = make_rig(models)
  write_colmap_model(root / folder, cameras, images, POINTS, binary)
  names = [f"view_{index:02d}.png" for index in range(len(models))]
  return write_images(root / "images", names, WIDTH, HEIGHT), camera_to_world


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "text"])
@pytest.mark.parametrize("kind", LENS_KINDS)
def test_every_supported_model_reads_back_exactly(tmp_path, kind, binary):
  models = LENS_KINDS[kind]
  images, camera_to_world = write_rig(tmp_path, models, binary)
  assert detect_format(tmp_path) == "colmap"
  dataset = load_dataset(tmp_path, split="all")

  assert dataset.image_names == tuple(f"images/view_{index:02d}.png"
                                      for index in range(len(models)))
  np.testing.assert_allclose(dataset.images, images, atol=0.5 / 255)
  cameras = dataset.cameras
  assert cameras.fisheye == (kind == "fisheye") and (cameras.width, cameras.height) == (8, 6)
  source_from_world = np.linalg.inv(np.asarray(dataset.world_from_source, np.float64))
  np.testing.assert_allclose(poses.transform_poses(source_from_world, cameras.camera_to_world),
                             camera_to_world, atol=2e-5)
  for index, (_, intrinsics, coefficients) in enumerate(models.values()):
    actual = [float(value[index]) for value in (cameras.fx, cameras.fy, cameras.cx, cameras.cy)]
    np.testing.assert_allclose(actual, intrinsics, rtol=1e-6)
    expected_distortion = np.zeros(8)
    expected_distortion[:len(coefficients)] = coefficients
    np.testing.assert_allclose(cameras.distortion[index], expected_distortion, rtol=1e-6)
  np.testing.assert_array_equal(colmap.read_capture(tmp_path).points, POINTS)


@pytest.mark.parametrize("folder", ["sparse", "."])
def test_the_model_is_found_in_sparse_or_the_root_and_sparse_0_wins(tmp_path, folder):
  write_rig(tmp_path, binary=False, folder=folder)
  assert colmap.model_folder(tmp_path) == tmp_path / folder
  assert load_dataset(tmp_path, split="all").num_images == len(PERSPECTIVE_MODELS)
  cameras, images, _ = make_rig(PERSPECTIVE_MODELS)
  write_colmap_model(tmp_path / "sparse" / "0", cameras, images[:3], POINTS, binary=True)
  assert colmap.model_folder(tmp_path) == tmp_path / "sparse" / "0"
  assert load_dataset(tmp_path, split="all").num_images == 3


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "text"])
@pytest.mark.parametrize("model", UNSUPPORTED)
def test_models_without_an_opencv_equivalent_name_the_camera_and_the_model(tmp_path, model,
                                                                           binary):
  cameras, images, _ = make_rig(PERSPECTIVE_MODELS)
  cameras[2] = colmap_model.ColmapCamera(13, model, WIDTH, HEIGHT, (4.0,) * UNSUPPORTED[model])
  write_colmap_model(tmp_path / "sparse" / "0", cameras, images, POINTS, binary)
  with pytest.raises(InputError, match=f"{model} model, which has no OpenCV equivalent") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path.endswith("cameras.bin" if binary else "cameras.txt")
  assert error.value.field == "camera 13"


@pytest.mark.parametrize("file_name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_or_padded_binary_files_name_the_file(tmp_path, file_name):
  write_rig(tmp_path)
  path = tmp_path / "sparse" / "0" / file_name
  data = path.read_bytes()
  for length in (3, 8, 20, len(data) // 2, len(data) - 1):
    path.write_bytes(data[:length])
    with pytest.raises(InputError, match="truncated") as error:
      load_dataset(tmp_path, split="all")
    assert error.value.path == str(path) and error.value.field
  path.write_bytes(data + b"\0\0")
  with pytest.raises(InputError, match="2 bytes follow the last record") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(path)


def test_a_corrupt_count_or_model_id_or_quaternion_names_the_record(tmp_path):
  write_rig(tmp_path)
  model = tmp_path / "sparse" / "0"
  cameras, images = (model / "cameras.bin").read_bytes(), (model / "images.bin").read_bytes()
  (model / "cameras.bin").write_bytes(np.uint64(10**12).tobytes() + cameras[8:])
  with pytest.raises(InputError, match="truncated") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.field == "number of cameras (1000000000000 records)"

  # The first camera's model id (after the count and its uint32 id).
  (model / "cameras.bin").write_bytes(cameras[:12] + np.int32(99).tobytes() + cameras[16:])
  with pytest.raises(InputError, match="unknown camera model id 99") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.field == "camera 11"

  (model / "cameras.bin").write_bytes(cameras)
  first_image_id = int(np.frombuffer(images, np.uint32, 1, 8)[0])
  (model / "images.bin").write_bytes(images[:12] + np.float64(3.0).tobytes() + images[20:])
  with pytest.raises(InputError, match="not a unit quaternion") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(model / "images.bin")
  assert error.value.field == f"image {first_image_id}"


def test_mixed_image_sizes_or_lens_kinds_name_the_camera(tmp_path):
  cameras, images, _ = make_rig(PERSPECTIVE_MODELS)
  cameras[3] = colmap_model.ColmapCamera(14, "PINHOLE", WIDTH + 2, HEIGHT, (7.0, 7.0, 5.0, 3.0))
  write_colmap_model(tmp_path / "sparse" / "0", cameras, images, POINTS, binary=True)
  with pytest.raises(InputError, match="mixed sizes") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.field == "camera 14"

  cameras[3] = colmap_model.ColmapCamera(14, "OPENCV_FISHEYE", WIDTH, HEIGHT, (4.0,) * 8)
  write_colmap_model(tmp_path / "sparse" / "0", cameras, images, POINTS, binary=True)
  with pytest.raises(InputError, match="is a fisheye lens but camera 11 is a perspective") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path.endswith("cameras.bin") and error.value.field == "camera 14"


def test_an_image_of_an_unknown_camera_and_a_missing_image_file_name_the_image(tmp_path):
  write_rig(tmp_path, binary=False)
  (tmp_path / "images" / "view_02.png").unlink()
  with pytest.raises(InputError, match="not found") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path.endswith("view_02.png")
  # Image ids count down from 6 while names count up: view_02 is image 4.
  assert error.value.field == "images.txt: image 4.file_path"

  cameras, images, _ = make_rig(PERSPECTIVE_MODELS)
  write_colmap_model(tmp_path / "sparse" / "0", cameras[1:], images, POINTS, binary=False)
  with pytest.raises(InputError, match="its camera 11 is not in cameras.txt") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path.endswith("images.txt") and error.value.field == "image 6"


@pytest.mark.parametrize("line, field, message", [
    ("11 PINHOLE eight 6 7.0 7.0 4.0 3.0", "line 4", "not int"),
    ("11 PINHOLE 8 6 7.0 7.0 4.0", "camera 11", "PINHOLE has 4 parameters, got 3"),
    ("11 PINHOLE 8 6 7.0 7.0 4.0 x", "camera 11", "not float"),
    ("11 PINHOLE 8", "line 4", r"needs CAMERA_ID MODEL WIDTH HEIGHT PARAMS\[\]"),
    ("11 MYSTERY 8 6 1.0", "camera 11", "unknown camera model 'MYSTERY'"),
    ("11 PINHOLE 8 6 0.0 7.0 4.0 3.0", "camera 11", "positive focal length"),
])
def test_malformed_text_lines_name_the_line_or_camera(tmp_path, line, field, message):
  write_rig(tmp_path, binary=False)
  path = tmp_path / "sparse" / "0" / "cameras.txt"
  lines = path.read_text().splitlines()
  path.write_text("\n".join(lines[:3] + [line] + lines[4:]) + "\n")
  with pytest.raises(InputError, match=message) as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(path) and error.value.field == field


def test_a_model_without_registered_images_or_with_repeated_names(tmp_path):
  cameras, images, _ = make_rig(PERSPECTIVE_MODELS)
  write_colmap_model(tmp_path / "sparse" / "0", cameras, [], POINTS[:0], binary=True)
  with pytest.raises(InputError, match="holds no registered images"):
    load_dataset(tmp_path, split="all")
  images[1] = colmap_image(99, images[1].camera_id, images[0].name, ring_poses(1)[0])
  write_colmap_model(tmp_path / "sparse" / "0", cameras, images, POINTS, binary=True)
  with pytest.raises(InputError, match=f"names {images[0].name!r} again"):
    load_dataset(tmp_path, split="all")


@pytest.mark.shared_data
def test_fern_cameras_and_points_read_like_its_llff_poses(shared_data):
  model = shared_data / "llff" / "fern" / "sparse" / "0"
  (fern_camera,) = colmap_model.read_cameras(model / "cameras.bin").values()
  assert (fern_camera.model, fern_camera.width, fern_camera.height) == ("SIMPLE_RADIAL", 4032,
                                                                          3024)
  assert fern_camera.params[0] == pytest.approx(3260.5, abs=0.1)  # LLFF's hwf focal
  points = colmap_model.read_points(model / "points3D.bin")
  assert points.shape[1] == 3 and len(points) > 1000 and np.all(np.isfinite(points))


def rename_image(tmp_path, binary, old_name, name):
  """The rig with image `old_name` renamed to `name`; returns (images file, its image id)."""
  cameras, images, _ = make_rig(PERSPECTIVE_MODELS)
  write_rig(tmp_path, binary=binary)
  index = [image.name for image in images].index(old_name)
  image = images[index]
  images[index] = colmap_model.ColmapImage(image.image_id, image.quaternion, image.translation,
                                           image.camera_id, name)
  write_colmap_model(tmp_path / "sparse" / "0", cameras, images, POINTS, binary)
  return tmp_path / "sparse" / "0" / ("images.bin" if binary else "images.txt"), image.image_id


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "text"])
@pytest.mark.parametrize("escape", ["parent", "absolute", "symlink"])
def test_an_image_name_leading_outside_the_image_folder_names_the_model_file_and_image(
    tmp_path, binary, escape):
  secret = tmp_path / "elsewhere" / "secret.png"
  write_images(secret.parent, [secret.name], WIDTH, HEIGHT)  # Readable: it must not be read.
  dataset = tmp_path / "dataset"
  name = {"parent": "../../elsewhere/secret.png", "absolute": str(secret),
          "symlink": "link.png"}[escape]
  images_path, image_id = rename_image(dataset, binary, "view_02.png", name)
  if escape == "symlink":
    (dataset / "images" / "link.png").symlink_to(secret)
  with pytest.raises(InputError, match="points outside") as error:
    load_dataset(dataset, split="all")
  assert error.value.path == str(images_path) and error.value.field == f"image {image_id}"


def test_an_image_name_in_a_subfolder_of_the_image_folder_reads(tmp_path):
  rename_image(tmp_path, False, "view_02.png", "camera_b/./view_02.png")
  write_images(tmp_path / "images" / "camera_b", ["view_02.png"], WIDTH, HEIGHT)
  (tmp_path / "images" / "view_02.png").unlink()
  dataset = load_dataset(tmp_path, split="all")
  assert "images/camera_b/./view_02.png" in dataset.image_names


def images_text_lines(tmp_path):
  """The rig written as text; (images.txt, its lines)."""
  write_rig(tmp_path, binary=False)
  path = tmp_path / "sparse" / "0" / "images.txt"
  return path, path.read_text().splitlines()


def test_images_txt_without_points_lines_is_refused_naming_the_line(tmp_path):
  # One line per image (some exporters write only the pose lines): read as two lines per image
  # it would silently lose every second image into a points line.
  path, lines = images_text_lines(tmp_path)
  comments, records = lines[:3], lines[3:]
  path.write_text("\n".join(comments + records[::2]) + "\n")
  with pytest.raises(InputError, match="reads as an image line") as error:
    load_dataset(tmp_path, split="all")
  # The first image's line is line 4, the second's (where points were expected) line 5.
  assert error.value.path == str(path) and error.value.field == "line 5"
  assert f"image {records[0].split()[0]}'s POINTS2D line" in str(error.value)


@pytest.mark.parametrize("points", ["1.5 2.5", "1.5 2.5 x", "# comment", "1.5 2.5 0.5"])
def test_a_malformed_points_line_names_the_line(tmp_path, points):
  path, lines = images_text_lines(tmp_path)
  lines[6] = points  # The second image's points line.
  path.write_text("\n".join(lines) + "\n")
  with pytest.raises(InputError, match="POINTS2D line must be empty or") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(path) and error.value.field == "line 7"


def test_images_txt_reads_every_image_with_any_points_lines(tmp_path):
  path, lines = images_text_lines(tmp_path)
  # Blank lines and comments between images, whitespace around points, 1e3 / nan / -inf
  # numbers, and the last image's points line missing at the end of the file.
  lines[4] = "  1e3 -2.5E-1 7   .5 nan -1  "
  lines[6] = "0 -inf 3"
  lines = lines[:5] + ["", "# another comment"] + lines[5:-1]
  path.write_text("\n".join(lines))
  images = colmap_model.read_images(path)
  assert len(images) == len(PERSPECTIVE_MODELS)
  assert load_dataset(tmp_path, split="all").num_images == len(PERSPECTIVE_MODELS)
