"""The catalogue's captures and weights (issue 68): paths a COLMAP model or a weights index names
that lead outside their folder, an images.txt without its points lines, poses_bounds.npy of
complex or text values, and NeuS projections that are singular however they are scaled. Each is
a `signerf` command that must end in one clear error naming the file and the entry (the shape of
test_bad_input_catalogue.py's command cases): a capture's before the command creates anything;
the weights' when they load, after the edit's first stages (`check_pipeline` reads no index)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file

from signerf_jax import camera, files
from signerf_jax.data import colmap_model
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from test_bad_input_catalogue import assert_one_clear_error, copy, edit_argv, inputs  # noqa: F401

# The data tests' writers of COLMAP and NeuS files (tests/data is not a package).
sys.path.insert(0, str(Path(__file__).parent / "data"))
from capture_writers import (colmap_image, neus_world_mat, write_colmap_model,  # noqa: E402
                             write_images)

WIDTH, HEIGHT, FOCAL, VIEWS = 16, 12, 14.0, 5


def ring(count: int = VIEWS) -> np.ndarray:
  """[count, 3, 4] OpenGL camera-to-world on a ring around the origin, looking at it."""
  angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
  eyes = np.stack([3 * np.cos(angles), 3 * np.sin(angles), np.full(count, 0.8)], -1)
  return np.asarray(camera.look_at(eyes.astype(np.float32), np.zeros(3, np.float32)), np.float64)


def colmap_scene(root: Path, binary: bool, names: list[str] | None = None) -> Path:
  """A 5-view COLMAP capture in `root` whose images are named `names` in the model (the files
  are view_<i>.png); returns the images file."""
  names = names or [f"view_{index}.png" for index in range(VIEWS)]
  cameras = [colmap_model.ColmapCamera(1, "PINHOLE", WIDTH, HEIGHT,
                                       (FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2))]
  images = [colmap_image(index + 1, 1, name, pose)
            for index, (name, pose) in enumerate(zip(names, ring()))]
  write_colmap_model(root / "sparse" / "0", cameras, images, np.zeros((3, 3)), binary)
  write_images(root / "images", [f"view_{index}.png" for index in range(VIEWS)], WIDTH, HEIGHT)
  return root / "sparse" / "0" / ("images.bin" if binary else "images.txt")


def train_argv(tmp_path: Path, scene: Path) -> list[str]:
  return ["train", "--data", str(scene), "--run", str(tmp_path / "r"), "--steps", "1"]


# Each case: (tmp_path, inputs) -> (argv, fragments the error line must hold, a path the
# command must not have created).
def colmap_image_name_climbing_out(tmp_path, inputs):
  # A readable image outside the dataset: the name must be refused, not the file found missing.
  write_images(tmp_path, ["secret.png"], WIDTH, HEIGHT)
  names = [f"view_{index}.png" for index in range(VIEWS)]
  names[3] = "../../../secret.png"
  images_path = colmap_scene(tmp_path / "scene" / "a", binary=False, names=names)
  return (train_argv(tmp_path, tmp_path / "scene" / "a"),
          [str(images_path), "image 4", "'../../../secret.png' points outside"], tmp_path / "r")


def colmap_absolute_image_name(tmp_path, inputs):
  write_images(tmp_path, ["secret.png"], WIDTH, HEIGHT)
  names = [f"view_{index}.png" for index in range(VIEWS)]
  names[1] = str(tmp_path / "secret.png")
  images_path = colmap_scene(tmp_path / "scene", binary=True, names=names)
  return (train_argv(tmp_path, tmp_path / "scene"),
          [str(images_path), "image 2", "points outside"], tmp_path / "r")


def colmap_images_txt_without_points_lines(tmp_path, inputs):
  images_path = colmap_scene(tmp_path / "scene", binary=False)
  lines = images_path.read_text().splitlines()
  # The pose lines only: read two lines per image, every second image would vanish silently.
  images_path.write_text("\n".join(lines[:3] + lines[3::2]) + "\n")
  return (train_argv(tmp_path, tmp_path / "scene"),
          [str(images_path), "line 5", "reads as an image line", "image 1's POINTS2D line"],
          tmp_path / "r")


def llff_scene(root: Path, rows_of=lambda rows: rows) -> Path:
  """A 5-view LLFF capture whose poses_bounds.npy rows are `rows_of(rows)`; returns its path."""
  (root / "images").mkdir(parents=True)
  rows = []
  for index, pose in enumerate(ring()):
    files.write_image(root / "images" / f"{index:03d}.png", np.full((HEIGHT, WIDTH, 3), 0.5))
    right, up, back, position = pose.T
    llff = np.stack([-up, right, back, position, [HEIGHT, WIDTH, FOCAL]], -1)
    rows.append(np.concatenate([llff.ravel(), [1.0, 10.0]]))
  np.save(root / "poses_bounds.npy", rows_of(np.asarray(rows)))
  return root / "poses_bounds.npy"


def llff_complex_poses(tmp_path, inputs):
  path = llff_scene(tmp_path / "llff", lambda rows: rows * (1 + 0.5j))
  return (train_argv(tmp_path, tmp_path / "llff"), [str(path), "dtype complex128"],
          tmp_path / "r")


def llff_poses_with_a_string_entry(tmp_path, inputs):
  path = llff_scene(tmp_path / "llff", lambda rows: np.where(
      np.arange(rows.size).reshape(rows.shape) == 7, "unknown", rows))
  return (train_argv(tmp_path, tmp_path / "llff"), [str(path), "dtype <U32"], tmp_path / "r")


def neus_singular_world_mat_at_a_huge_scale(tmp_path, inputs):
  scene = tmp_path / "neus"
  scene.mkdir()
  arrays = {f"world_mat_{index}": neus_world_mat(pose, FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2,
                                                  scale=1e300)
            for index, pose in enumerate(ring())}
  arrays["world_mat_3"][:3, 2] = 0.0  # Scaled or not, no camera projects like this.
  np.savez(scene / "cameras_sphere.npz", **arrays)
  write_images(scene / "image", [f"{index:03d}.png" for index in range(VIEWS)], WIDTH, HEIGHT)
  return (train_argv(tmp_path, scene),
          [str(scene / "cameras_sphere.npz"), "world_mat_3", "is singular"], tmp_path / "r")


def weights_index_leading_outside_the_model(tmp_path, inputs):
  model = copy(DEFAULT_MODEL_DIR, tmp_path / "model")
  weights = model / "vae" / "diffusion_pytorch_model.safetensors"
  # The VAE's weights moved out of the model: an index naming them must not reach them.
  outside = tmp_path / "outside.safetensors"
  shutil.move(weights, outside)
  first, *others = sorted(load_file(outside))
  index = model / "vae" / "diffusion_pytorch_model.safetensors.index.json"
  index.write_text(json.dumps({"weight_map": {name: "../../outside.safetensors"
                                              for name in [first, *others]}}))
  argv = edit_argv(tmp_path, inputs, "--model", str(model))
  box = argv.index("--box") + 1
  # A box inside the scene's bounds ([-0.95, -0.95, -0.15] .. [0.95, 0.95, 0.525]), so that the
  # edit gets as far as loading the weights.
  argv[box:box + 6] = ["-0.2", "-0.2", "-0.1", "0.2", "0.2", "0.3"]
  return argv, [str(index), f"weight_map[{first!r}]", "points outside"], None


CAPTURE_CASES = [
    colmap_image_name_climbing_out, colmap_absolute_image_name,
    colmap_images_txt_without_points_lines, llff_complex_poses, llff_poses_with_a_string_entry,
    neus_singular_world_mat_at_a_huge_scale, weights_index_leading_outside_the_model,
]


@pytest.mark.parametrize("case", CAPTURE_CASES, ids=lambda case: case.__name__)
def test_a_bad_capture_or_weights_path_is_one_clear_error(tmp_path, inputs, capsys, case):
  assert_one_clear_error(*case(tmp_path, inputs), capsys)
