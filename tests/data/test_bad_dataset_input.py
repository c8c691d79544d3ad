"""Every kind of bad dataset input raises InputError naming the file and the field at fault."""

import numpy as np
import pytest

from signerf_jax import files
from signerf_jax.data import load_dataset, write_nerfstudio
from signerf_jax.errors import InputError


def set_key(path, value):
  """A mutation of the transforms.json dict: sets the value at `path` (keys and indices)."""
  def mutate(meta):
    target = meta
    for key in path[:-1]:
      target = target[key]
    target[path[-1]] = value
  return mutate


def delete_key(path):
  def mutate(meta):
    target = meta
    for key in path[:-1]:
      target = target[key]
    del target[path[-1]]
  return mutate


def scale_rotation(factor):
  def mutate(meta):
    matrix = np.asarray(meta["frames"][3]["transform_matrix"])
    matrix[:3, :3] *= factor
    meta["frames"][3]["transform_matrix"] = matrix.tolist()
  return mutate


def reflect(meta):
  matrix = np.asarray(meta["frames"][3]["transform_matrix"])
  matrix[:3, 0] *= -1
  meta["frames"][3]["transform_matrix"] = matrix.tolist()


def shear(meta):
  matrix = np.asarray(meta["frames"][3]["transform_matrix"])
  matrix[:3, 0] += 0.01 * matrix[:3, 1]
  meta["frames"][3]["transform_matrix"] = matrix.tolist()


def per_frame_width(meta):
  meta["frames"][2]["w"] = meta["w"] + 2


def opencv_with_polynomial_k4(meta):
  """nerfstudio's OPENCV k4 is an r^8 term (OpenCV's k4 divides): it cannot be represented."""
  meta["camera_model"] = "OPENCV"
  meta["frames"][1]["k4"] = 0.01


TRANSFORMS_CASES = {
    "missing frames": (delete_key(["frames"]), "frames"),
    "empty frames": (set_key(["frames"], []), "frames"),
    "frames not a list": (set_key(["frames"], {"0": {}}), "frames"),
    "frame not an object": (set_key(["frames", 2], [1, 2]), "frames[2]"),
    "missing transform_matrix": (delete_key(["frames", 3, "transform_matrix"]),
                                 "frames[3].transform_matrix"),
    "transform_matrix 3x3": (set_key(["frames", 3, "transform_matrix"], np.eye(3).tolist()),
                             "frames[3].transform_matrix"),
    "transform_matrix ragged": (set_key(["frames", 3, "transform_matrix"], [[1, 0], [0]]),
                                "frames[3].transform_matrix"),
    "transform_matrix text": (set_key(["frames", 3, "transform_matrix"], "identity"),
                              "frames[3].transform_matrix"),
    "transform_matrix NaN": (set_key(["frames", 3, "transform_matrix", 0, 3], float("nan")),
                             "frames[3].transform_matrix"),
    "transform_matrix infinite": (set_key(["frames", 3, "transform_matrix", 1, 1], float("inf")),
                                  "frames[3].transform_matrix"),
    "bad last row": (set_key(["frames", 3, "transform_matrix", 3], [0, 0, 1, 1]),
                     "frames[3].transform_matrix"),
    "scaled rotation": (scale_rotation(1.01), "frames[3].transform_matrix"),
    "sheared rotation": (shear, "frames[3].transform_matrix"),
    "reflection": (reflect, "frames[3].transform_matrix"),
    "zero focal": (set_key(["fl_x"], 0.0), "fl_x"),
    "negative per-frame focal": (set_key(["frames", 2, "fl_y"], -5.0), "frames[2].fl_y"),
    "focal as text": (set_key(["fl_x"], "ten"), "fl_x"),
    "missing focal": (delete_key(["fl_x"]), "frames[0].fl_x"),
    "missing width": (delete_key(["w"]), "frames[0].w"),
    "fractional width": (set_key(["w"], 12.5), "w"),
    "non-finite principal point": (set_key(["cx"], float("nan")), "cx"),
    "mixed declared sizes": (per_frame_width, "frames[2].w"),
    "missing file_path": (delete_key(["frames", 1, "file_path"]), "frames[1].file_path"),
    "unsupported camera model": (set_key(["camera_model"], "EQUIRECTANGULAR"), "camera_model"),
    "OPENCV with k4": (opencv_with_polynomial_k4, "frames[1].k4"),
    "bad applied_transform": (set_key(["applied_transform"], [[1, 0, 0]]), "applied_transform"),
    "bad scene_bounds": (set_key(["signerf", "scene_bounds"], [[1, 1, 1], [0, 0, 0]]),
                         "signerf.scene_bounds"),
    "bad scene_kind": (set_key(["signerf", "scene_kind"], "indoor"), "signerf.scene_kind"),
    "bad depth unit": (set_key(["depth_unit_scale_factor"], -1e-3), "depth_unit_scale_factor"),
}


@pytest.fixture
def written(tmp_path, dataset_factory):
  dataset = dataset_factory(count=5, width=12, height=9, with_extras=False)
  return write_nerfstudio(tmp_path, dataset)


@pytest.mark.parametrize("case", TRANSFORMS_CASES)
def test_malformed_transforms_json_names_file_and_field(written, case):
  mutate, field = TRANSFORMS_CASES[case]
  meta = files.read_json(written)
  mutate(meta)
  files.write_json(written, meta)
  with pytest.raises(InputError) as error:
    load_dataset(written.parent, split="all")
  assert error.value.path == str(written)
  assert error.value.field == field
  assert str(written) in str(error.value) and field in str(error.value)


def test_split_files_mixing_fisheye_and_perspective_lenses_name_the_camera_model(
    tmp_path, dataset_factory):
  written = write_nerfstudio(tmp_path, dataset_factory(count=4, with_extras=False))
  meta = files.read_json(written)
  written.unlink()
  for split, frames, camera_model in (("train", meta["frames"][:3], "PINHOLE"),
                                      ("test", meta["frames"][3:], "OPENCV_FISHEYE")):
    files.write_json(tmp_path / f"transforms_{split}.json",
                     {**meta, "camera_model": camera_model, "frames": frames})
  with pytest.raises(InputError, match="mix fisheye and perspective") as error:
    load_dataset(tmp_path, split="all")
  assert error.value.path == str(tmp_path / "transforms_test.json")
  assert error.value.field == "camera_model"


def test_invalid_json_names_the_file(written):
  written.write_text('{"frames": [')
  with pytest.raises(InputError, match="not valid JSON") as error:
    load_dataset(written.parent)
  assert error.value.path == str(written)


def test_missing_training_image_names_file_and_frame(written):
  (written.parent / "images" / "frame_00002.png").unlink()
  with pytest.raises(InputError, match="not found") as error:
    load_dataset(written.parent, split="train", eval_every=4)
  assert error.value.path.endswith("frame_00002.png")
  assert error.value.field == "frames[2].file_path"


def test_image_of_a_different_size_names_file_and_frame(written):
  files.write_image(written.parent / "images" / "frame_00003.png", np.zeros((9, 10, 3)))
  with pytest.raises(InputError, match="is 10x9 pixels, not the 12x9 of transforms.json's w and h") as error:
    load_dataset(written.parent, split="all")
  assert error.value.path.endswith("frame_00003.png")
  assert error.value.field == "frames[3].file_path"


@pytest.mark.parametrize("argument, field", [
    ({"split": "test"}, "split"), ({"downscale": 0}, "downscale"),
    ({"downscale": 1.5}, "downscale"), ({"scene_kind": "indoor"}, "scene_kind"),
    ({"eval_every": 1}, "eval_every")])
def test_bad_arguments_name_the_parameter(written, argument, field):
  with pytest.raises(InputError) as error:
    load_dataset(written.parent, **argument)
  assert error.value.field == field


def test_unknown_directory_contents(tmp_path):
  with pytest.raises(InputError, match="unknown dataset format"):
    load_dataset(tmp_path)
  with pytest.raises(InputError, match="not found"):
    load_dataset(tmp_path / "absent")
