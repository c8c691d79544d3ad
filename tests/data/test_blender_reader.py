
import numpy as np
import pytest

from signerf_jax import camera, files
from signerf_jax.data import load_dataset, poses
from signerf_jax.errors import InputError

ANGLE = 0.6911112070083618


def write_blender_scene(root, train_count=3, test_count=2, missing_test=(1,), size=8):
  """A tiny Blender scene: cameras on a circle of radius 4, half-transparent red RGBA images."""
  for split, count in (("train", train_count), ("test", test_count)):
    frames = []
    for index in range(count):
      angle = 2 * np.pi * index / count + (0.3 if split == "test" else 0.0)
      eye = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.0], np.float32)
      pose = np.concatenate([np.asarray(camera.look_at(eye, np.zeros(3, np.float32))),
                             [[0, 0, 0, 1]]])
      frames.append({"file_path": f"./{split}/r_{index}", "transform_matrix": pose.tolist()})
      if split == "test" and index in missing_test:
        continue
      rgba = np.zeros((size, size, 4), np.float32)
      rgba[..., 0], rgba[..., 3] = 1.0, 0.5
      files.write_image(root / split / f"r_{index}.png", rgba)
    files.write_json(root / f"transforms_{split}.json",
                     {"camera_angle_x": ANGLE, "frames": frames})


def test_blender_reader_composites_normalises_and_skips_missing_test_images(tmp_path):
  write_blender_scene(tmp_path)
  train = load_dataset(tmp_path, background_color=(0.0, 0.0, 1.0))
  assert train.scene_kind == "bounded" and train.num_images == 3
  np.testing.assert_allclose(train.images, np.broadcast_to([0.5, 0, 0.5], (3, 8, 8, 3)),
                             atol=1 / 255)
  np.testing.assert_allclose(train.cameras.fx, 0.5 * 8 / np.tan(ANGLE / 2), rtol=1e-6)
  # The [-1.5, 1.5]^3 Blender box becomes the unit box: radius 4 -> 8/3.
  np.testing.assert_allclose(np.linalg.norm(train.cameras.positions, axis=-1),
                             np.sqrt(17) / 1.5, rtol=1e-5)
  np.testing.assert_allclose(train.world_from_source, poses.similarity(1 / 1.5), atol=1e-7)
  near, far = poses.near_far_for_box(train.cameras, *train.scene_bounds)
  assert (train.near, train.far) == (near, far)

  with pytest.warns(UserWarning, match=r"skipped 1 frames.*test/r_1\.png"):
    test = load_dataset(tmp_path, split="eval", downscale=2)
  assert test.image_names == ("test/r_0.png",)
  assert (test.width, test.height) == (4, 4)
  np.testing.assert_allclose(test.cameras.fx, 0.25 * 8 / np.tan(ANGLE / 2), rtol=1e-6)
  with pytest.warns(UserWarning):
    assert load_dataset(tmp_path, split="all").num_images == 4


def test_blender_missing_train_image_is_an_error(tmp_path):
  write_blender_scene(tmp_path)
  (tmp_path / "train" / "r_2.png").unlink()
  with pytest.raises(InputError) as error:
    load_dataset(tmp_path)
  assert error.value.path.endswith("transforms_train.json")
  assert error.value.field == "frames[2].file_path"


@pytest.mark.parametrize("angle", [0.0, -0.5, 3.5, "wide", None])
def test_blender_bad_field_of_view(tmp_path, angle):
  write_blender_scene(tmp_path)
  meta = files.read_json(tmp_path / "transforms_train.json")
  meta["camera_angle_x"] = angle
  files.write_json(tmp_path / "transforms_train.json", meta)
  with pytest.raises(InputError) as error:
    load_dataset(tmp_path)
  assert error.value.field == "camera_angle_x"


def test_blender_images_of_mixed_sizes(tmp_path):
  write_blender_scene(tmp_path)
  files.write_image(tmp_path / "train" / "r_1.png", np.zeros((8, 6, 4)))
  with pytest.raises(InputError, match="is 6x8 pixels, not the 8x8 of the first image") as error:
    load_dataset(tmp_path)
  assert error.value.path.endswith("r_1.png")
  assert "frames[1].file_path" in error.value.field


@pytest.mark.shared_data
def test_lego_cameras_look_at_the_origin_and_see_the_model(shared_data):
  with pytest.warns(UserWarning, match="skipped 175 frames"):
    lego = load_dataset(shared_data / "nerf_synthetic" / "lego", split="eval", downscale=8)
  assert lego.num_images == 25 and (lego.width, lego.height) == (100, 100)
  assert lego.image_names[:2] == ("test/r_0.png", "test/r_8.png")
  np.testing.assert_allclose(lego.cameras.fx, 1111.111 / 8, rtol=1e-4)
  positions, forward = np.asarray(lego.cameras.positions), np.asarray(lego.cameras.forward)
  # Distance from the origin to each optical axis: they all pass through the origin region.
  along = np.sum(-positions * forward, -1, keepdims=True)
  assert np.max(np.linalg.norm(-positions - along * forward, axis=-1)) < 0.05
  assert np.all(np.abs(lego.cameras.positions) <= 4.1 / 1.5)
  # Every non-background pixel lies inside the projection of the scene bounds.
  corners = np.stack(np.meshgrid(*zip(*lego.scene_bounds), indexing="ij"), -1).reshape(-1, 3)
  pixels, depth = map(np.asarray, camera.project(lego.cameras, corners))
  assert np.all(depth > 0)
  distances = np.linalg.norm(corners[None] - positions[:, None], axis=-1)
  assert np.all((distances >= lego.near - 1e-6) & (distances <= lego.far + 1e-6))
  foreground = np.any(lego.images < 0.99, axis=-1)
  rows, columns = np.mgrid[:100, :100] + 0.5
  for index in range(lego.num_images):
    lower, upper = np.min(pixels[index], 0), np.max(pixels[index], 0)
    assert foreground[index].sum() > 500
    seen_columns, seen_rows = columns[foreground[index]], rows[foreground[index]]
    assert np.all((seen_columns >= lower[0]) & (seen_columns <= upper[0]))
    assert np.all((seen_rows >= lower[1]) & (seen_rows <= upper[1]))


def test_blender_scene_whose_test_images_are_all_missing_names_the_test_file(tmp_path):
  write_blender_scene(tmp_path, missing_test=(0, 1))
  with pytest.warns(UserWarning, match="skipped 2 frames"):
    assert load_dataset(tmp_path).num_images == 3  # Training needs no test image.
  with pytest.warns(UserWarning), pytest.raises(
      InputError, match="test split's images are all missing") as error:
    load_dataset(tmp_path, split="eval")
  # Not eval_every, which nobody gave: the file whose images are missing.
  assert error.value.path == str(tmp_path / "transforms_test.json")
  assert error.value.field == "frames"
  with pytest.warns(UserWarning):  # Holding out training views instead works.
    assert load_dataset(tmp_path, split="eval", eval_every=2).num_images == 2


def test_blender_scene_without_a_test_file_names_it(tmp_path):
  write_blender_scene(tmp_path)
  (tmp_path / "transforms_test.json").unlink()
  with pytest.raises(InputError, match="file not found") as error:
    load_dataset(tmp_path, split="eval")
  assert error.value.path == str(tmp_path / "transforms_test.json")


@pytest.mark.parametrize("outside", ["../secret", "/etc/hostname", "./train/link"])
def test_blender_file_path_outside_the_scene_is_refused(tmp_path, outside):
  scene = tmp_path / "scene"
  write_blender_scene(scene)
  files.write_image(tmp_path / "secret.png", np.zeros((8, 8, 4)))
  (scene / "train" / "link.png").symlink_to(tmp_path / "secret.png")
  meta = files.read_json(scene / "transforms_train.json")
  meta["frames"][1]["file_path"] = outside
  files.write_json(scene / "transforms_train.json", meta)
  with pytest.raises(InputError, match="points outside the folder") as error:
    load_dataset(scene)
  assert error.value.path == str(scene / "transforms_train.json")
  assert error.value.field == "frames[1].file_path"


def test_blender_image_listed_twice_names_both_entries(tmp_path):
  write_blender_scene(tmp_path, missing_test=())
  meta = files.read_json(tmp_path / "transforms_test.json")
  meta["frames"][1]["file_path"] = "train/r_2.png"  # A training view held out too.
  files.write_json(tmp_path / "transforms_test.json", meta)
  with pytest.raises(InputError, match=r"transforms_train.json's frames\[2\].file_path") as error:
    load_dataset(tmp_path)
  assert error.value.path == str(tmp_path / "transforms_test.json")
  assert error.value.field == "frames[1].file_path"
  meta = files.read_json(tmp_path / "transforms_train.json")
  meta["frames"][0]["file_path"] = "./train/r_1"  # One file listing an image twice.
  files.write_json(tmp_path / "transforms_train.json", meta)
  with pytest.raises(InputError, match=r"frames\[0\].file_path") as error:
    load_dataset(tmp_path)
  assert error.value.field == "frames[1].file_path"
