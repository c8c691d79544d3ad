"""The catalogue of bad inputs (issue 17): at least one case of every class found by trying the
commands as a hostile or careless user would. Each runs as the user meets it — a `signerf`
command on a small scene and run, or the loader a command calls — and must end in a clear error
naming the file or the parameter at fault: exit code 2 and one "error:" line, never a traceback,
a silently wrong result or a misleading message; and nothing half-written."""

from __future__ import annotations

import errno
import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

from signerf_jax import cli, files, ownership
from signerf_jax.diffusion import pipeline
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from signerf_jax.editing.project import load_arrays, save_arrays
from signerf_jax.errors import InputError


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
  """A 5-view 16 px scene and a NeRF trained on it for 2 steps (read-only: cases copy them)."""
  root = tmp_path_factory.mktemp("catalogue")
  assert cli.main(["synthesize", "--out", str(root / "scene"),
                   "--gin_param", "synthetic_cameras.num_views = 5",
                   "--gin_param", "synthetic_cameras.image_size = 16",
                   "--gin_param", "synthetic_scene.num_meshes = 0"]) == 0
  assert cli.main(["train", "--data", str(root / "scene"), "--run", str(root / "run"),
                   "--steps", "2", "--skip_eval"]) == 0
  return {"scene": root / "scene", "run": root / "run"}


def copy(source: Path, destination: Path) -> Path:
  shutil.copytree(source, destination)
  return destination


def run_command(argv: list[str], capsys) -> tuple[int, str]:
  """(exit code, stderr) of `signerf ARGV`; a usage error's SystemExit is its exit code."""
  capsys.readouterr()
  try:
    code = cli.main(argv)
  except SystemExit as exit_:
    code = exit_.code
  return code, capsys.readouterr().err


def png_header(width: int, height: int) -> bytes:
  """A PNG that claims width x height and holds no pixels (a decompression bomb's header)."""
  chunk = lambda kind, body: (struct.pack(">I", len(body)) + kind + body
                              + struct.pack(">I", zlib.crc32(kind + body)))
  return (files.PNG_SIGNATURE + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0,
                                                           0)) + chunk(b"IEND", b""))


def edit_argv(tmp_path: Path, inputs, *extra: str) -> list[str]:
  return ["edit", "--edit", str(tmp_path / "edit"), "--run", str(inputs["run"]), "--prompt",
          "a red cow", "--box", "-0.2", "-0.2", "-0.2", "0.2", "0.2", "0.2", *extra]


# Each case: (tmp_path, inputs) -> (argv, fragments the error line must hold, a path the
# command must not have created). One or more per class of the findings.
def gin_file_with_import(tmp_path, inputs):
  evil = tmp_path / "evil.gin"
  evil.write_text("TrainConfig.steps = 3\nimport os\n")
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--gin_file",
           str(evil)], [str(evil), "line 2", "would run code"], tmp_path / "r")


def saved_run_config_with_import(tmp_path, inputs):
  run = copy(inputs["run"], tmp_path / "run")
  with open(run / "config.gin", "a") as handle:
    handle.write("from os import system\n")
  return (["train", "--data", str(inputs["scene"]), "--run", str(run), "--steps", "3"],
          [str(run / "config.gin"), "would run code"], None)


def saved_edit_config_with_import(tmp_path, inputs):
  (tmp_path / "edit").mkdir()
  (tmp_path / "edit" / "config.gin").write_text("import signerf_jax.planted\n")
  return (edit_argv(tmp_path, inputs), [str(tmp_path / "edit" / "config.gin"), "line 1"], None)


def truncated_image(tmp_path, inputs):
  scene = copy(inputs["scene"], tmp_path / "scene")
  image = scene / "images" / "frame_00002.png"
  image.write_bytes(image.read_bytes()[:200])
  return (["train", "--data", str(scene), "--run", str(tmp_path / "r"), "--steps", "1"],
          [str(image), "truncated"], tmp_path / "r")


def flipped_checkpoint_byte(tmp_path, inputs):
  run = copy(inputs["run"], tmp_path / "run")
  data = bytearray((run / "checkpoint.msgpack").read_bytes())
  data[len(data) // 2] ^= 0x10
  (run / "checkpoint.msgpack").write_bytes(bytes(data))
  return (["eval", "--run", str(run)], [str(run / "checkpoint.msgpack"), "checksum"], None)


def truncated_checkpoint(tmp_path, inputs):
  run = copy(inputs["run"], tmp_path / "run")
  path = run / "checkpoint.msgpack"
  path.write_bytes(path.read_bytes()[:1000])
  return (["eval", "--run", str(run)], [str(path), "not a readable checkpoint (truncated"], None)


def negative_learning_rate(tmp_path, inputs):
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--gin_param",
           "TrainConfig.learning_rate = -0.01"],
          ["TrainConfig.learning_rate", "must be a finite number > 0 or None, got -0.01"], tmp_path / "r")


def negative_steps(tmp_path, inputs):
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--steps",
           "-5"], ["argument --steps", "must be an integer >= 1, got -5"], tmp_path / "r")


def negative_max_seconds_in_a_scope(tmp_path, inputs):
  return (edit_argv(tmp_path, inputs, "--gin_param", "finetune/TrainConfig.max_seconds = -1"),
          ["finetune/TrainConfig.max_seconds", "got -1"], tmp_path / "edit" / "stages.json")


def text_for_an_integer(tmp_path, inputs):
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--gin_param",
           "TrainConfig.steps = 'abc'"], ["TrainConfig.steps", "got 'abc'"], tmp_path / "r")


def list_for_a_learning_rate(tmp_path, inputs):
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--gin_param",
           "TrainConfig.learning_rate = [0.01, 0.001]"],
          ["TrainConfig.learning_rate", "got [0.01, 0.001]"], tmp_path / "r")


def zero_rays_per_batch(tmp_path, inputs):
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--gin_param",
           "CapacityRules.rays_per_batch = 0"],
          ["CapacityRules.rays_per_batch", "an integer >= 1 or None, got 0"], tmp_path / "r")


def one_image_dataset(tmp_path, inputs):
  scene = copy(inputs["scene"], tmp_path / "scene")
  meta = json.loads((scene / "transforms.json").read_text())
  meta["frames"] = meta["frames"][:1]
  (scene / "transforms.json").write_text(json.dumps(meta))
  return (["train", "--data", str(scene), "--run", str(tmp_path / "r")],
          [str(scene), "the train split is empty"], tmp_path / "r")


def model_config_that_is_a_list(tmp_path, inputs):
  model = copy(DEFAULT_MODEL_DIR, tmp_path / "model")
  (model / "unet" / "config.json").write_text("[]")
  return (edit_argv(tmp_path, inputs, "--model", str(model)),
          [str(model / "unet" / "config.json"), "expected a JSON object"],
          tmp_path / "edit" / "stages.json")


def downscale_beyond_the_image(tmp_path, inputs):
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), "--downscale",
           "64"], ["downscale", "64 leaves no pixel of the 16x16 images"], tmp_path / "r")


def run_names_a_file(tmp_path, inputs):
  (tmp_path / "taken").write_text("")
  return (["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "taken")],
          [str(tmp_path / "taken"), ": run: names a file"], None)


def out_under_a_file(tmp_path, inputs):
  (tmp_path / "taken").write_text("")
  return (["synthesize", "--out", str(tmp_path / "taken" / "scene")],
          ["out", f"cannot be created: {tmp_path / 'taken'} is a file"], None)


def box_with_nan(tmp_path, inputs):
  argv = edit_argv(tmp_path, inputs)
  argv[argv.index("--box") + 2] = "nan"
  return argv, ["argument --box", "must be a finite number, got nan"], tmp_path / "edit"


def garbage_proxy_mesh(tmp_path, inputs):
  mesh = tmp_path / "proxy.obj"
  mesh.write_bytes(np.random.default_rng(0).bytes(3000))
  argv = edit_argv(tmp_path, inputs)
  box = argv.index("--box")
  argv[box:box + 7] = ["--proxy", str(mesh), "--on_ground", "0", "0", "0"]
  return argv, [str(mesh), "proxy"], tmp_path / "edit" / "stages.json"


def llff_hwf_that_disagrees_with_the_images(tmp_path, inputs):
  scene = tmp_path / "llff"
  (scene / "images").mkdir(parents=True)
  rows = []
  for index in range(4):
    files.write_image(scene / "images" / f"{index:03d}.png", np.full((12, 16, 3), 0.5))
    pose = np.concatenate([np.eye(3), [[0.1 * index], [0.0], [0.0]]], axis=1)
    hwf = [[120.0], [160.0], [100.0]]  # 120 x 160 claimed; the images are 12 x 16.
    rows.append(np.concatenate([np.concatenate([pose, hwf], axis=1).ravel(), [1.0, 10.0]]))
  np.save(scene / "poses_bounds.npy", np.asarray(rows))
  return (["train", "--data", str(scene), "--run", str(tmp_path / "r")],
          [str(scene / "images"), "is 16x12 pixels, not the 160x120 of poses_bounds.npy's hwf"],
          tmp_path / "r")


def decompression_bomb(tmp_path, inputs):
  scene = copy(inputs["scene"], tmp_path / "scene")
  bomb = scene / "images" / "frame_00001.png"
  bomb.write_bytes(png_header(100_000, 100_000))
  return (["train", "--data", str(scene), "--run", str(tmp_path / "r")],
          [str(bomb), "100000x100000 pixels is more than"], tmp_path / "r")


def place_pixel_outside_the_view(tmp_path, inputs):
  return (["place", "--run", str(inputs["run"]), "--edit", str(tmp_path / "edit"), "--view", "0",
           "--pixel", "500", "5", "--proxy", "primitive:cow"],
          ["pixel", "(500, 5) is outside the 16x16 view"], tmp_path / "edit")


def place_without_a_target(tmp_path, inputs):
  return (["place", "--run", str(inputs["run"]), "--edit", str(tmp_path / "edit"), "--view", "0"],
          ["give --view, --pixel and --proxy"], tmp_path / "edit")


def run_is_the_dataset(tmp_path, inputs):
  scene = copy(inputs["scene"], tmp_path / "scene")
  return (["train", "--data", str(scene), "--run", str(scene), "--steps", "1"],
          [": run: is the input given as --data", "never writes into what it reads"],
          scene / "model.json")


def synthesize_over_a_capture(tmp_path, inputs):
  capture = copy(inputs["scene"], tmp_path / "capture")
  shutil.rmtree(capture / ownership.MARKER_FOLDER)  # A capture the user made, not signerf.
  return (["synthesize", "--out", str(capture)],
          [str(capture), "holds files signerf did not write", "nothing there is touched"],
          capture / ownership.MARKER_FOLDER)


def preview_into_a_run(tmp_path, inputs):
  run = copy(inputs["run"], tmp_path / "run")
  return (["preview", "--edit", str(run), "--data", str(inputs["scene"]), "--prompt", "a red cow",
           "--box", "-0.2", "-0.2", "-0.2", "0.2", "0.2", "0.2"],
          [f"{run}: edit: is a signerf run directory, not an edit directory"],
          run / "stages.json")


def resume_on_other_data(tmp_path, inputs):
  run = copy(inputs["run"], tmp_path / "run")
  other = copy(inputs["scene"], tmp_path / "other")
  return (["train", "--data", str(other), "--run", str(run), "--steps", "3"],
          [str(run / "model.json"), "fingerprint", "trained on other data", "--start_over"],
          None)


def resume_at_another_size(tmp_path, inputs):
  run = copy(inputs["run"], tmp_path / "run")
  return (["train", "--data", str(inputs["scene"]), "--run", str(run), "--downscale", "2",
           "--steps", "3"], ["images of 16x16 px then, 8x8 now", "downscale 1 then, 2 now"],
          None)


def eval_chunk_size_beyond_memory(tmp_path, inputs):
  return (["eval", "--run", str(inputs["run"]), "--chunk_size", "10000000000000"],
          ["--chunk_size", "more than this machine's"], None)


COMMAND_CASES = [
    gin_file_with_import, saved_run_config_with_import, saved_edit_config_with_import,
    truncated_image, flipped_checkpoint_byte, truncated_checkpoint, negative_learning_rate,
    negative_steps, negative_max_seconds_in_a_scope, text_for_an_integer,
    list_for_a_learning_rate, zero_rays_per_batch, one_image_dataset, model_config_that_is_a_list,
    downscale_beyond_the_image, run_names_a_file, out_under_a_file, box_with_nan,
    garbage_proxy_mesh, llff_hwf_that_disagrees_with_the_images, decompression_bomb,
    place_pixel_outside_the_view, place_without_a_target, run_is_the_dataset,
    synthesize_over_a_capture, preview_into_a_run, resume_on_other_data, resume_at_another_size,
    eval_chunk_size_beyond_memory,
]


def assert_one_clear_error(argv: list[str], fragments: list[str], not_created: Path | None,
                           capsys) -> None:
  """`signerf ARGV` ends in exit code 2 and one error line holding every fragment, with no
  traceback, and has not created `not_created` (when given). The catalogue's other files
  (test_bad_input_catalogue_*.py) import this with `inputs` and `run_command`."""
  code, error = run_command(argv, capsys)
  assert code == 2
  assert "Traceback" not in error
  message = error.strip().splitlines()[-1]
  assert f"signerf {argv[0]}: error:" in message or "error: argument" in message
  for fragment in fragments:
    assert fragment in message
  if not_created is not None:
    assert not not_created.exists()  # Refused before any work was done.


@pytest.mark.parametrize("case", COMMAND_CASES, ids=lambda case: case.__name__)
def test_a_bad_input_to_a_command_is_one_clear_error(tmp_path, inputs, capsys, case):
  assert_one_clear_error(*case(tmp_path, inputs), capsys)


def weights_with(tmp_path, change) -> Path:
  model = copy(DEFAULT_MODEL_DIR, tmp_path / "model")
  path = model / "vae" / "diffusion_pytorch_model.safetensors"
  tensors = load_file(path)
  name = sorted(name for name in tensors if name.endswith("weight"))[0]
  tensors[name] = change(tensors[name])
  save_file(tensors, path)
  return model, path, name


@pytest.mark.parametrize("change, problem", [
    (lambda weight: np.where(np.arange(weight.size).reshape(weight.shape) == 3, np.nan, weight),
     "NaN or infinite"),
    (lambda weight: weight.astype(np.int32), "int32 values"),
], ids=["nan", "integer"])
def test_weights_that_are_not_finite_floats_name_the_tensor_and_file(tmp_path, change, problem):
  model, path, name = weights_with(tmp_path, change)
  with pytest.raises(InputError, match=problem) as error:
    pipeline.load_pipeline(model)
  assert error.value.path == str(path) and error.value.field == name


@pytest.mark.parametrize("damage", [
    lambda path: path.write_bytes(path.read_bytes()[:300]),
    lambda path: path.write_bytes(b"not a zip file"),
    lambda path: save_arrays(path, other=np.zeros(3)),
], ids=["truncated", "garbage", "missing_array"])
def test_a_damaged_stage_output_names_the_file_and_the_remedy(tmp_path, damage):
  path = tmp_path / "views" / "frame_00000.npz"
  save_arrays(path, mask=np.ones((8, 8), np.float32), control=np.zeros((8, 8, 3), np.float32))
  damage(path)
  with pytest.raises(InputError, match=r"damaged stage output.*--redo") as error:
    load_arrays(path, ("mask", "control"))
  assert error.value.path == str(path)


def test_a_full_disk_while_checkpointing_names_the_file_and_keeps_the_last_checkpoint(
    tmp_path, inputs, capsys, monkeypatch):
  run = copy(inputs["run"], tmp_path / "run")
  checkpoint = (run / "checkpoint.msgpack").read_bytes()
  write_bytes = Path.write_bytes

  def full_disk_for_checkpoints(path, data):
    if "checkpoint" in path.name:
      raise OSError(errno.ENOSPC, "No space left on device")
    return write_bytes(path, data)

  monkeypatch.setattr(Path, "write_bytes", full_disk_for_checkpoints)
  assert_one_clear_error(["train", "--data", str(inputs["scene"]), "--run", str(run), "--steps",
                          "4", "--skip_eval"],
                         [str(run / "checkpoint.msgpack"), "No space left on device",
                          "is kept"], None, capsys)
  assert (run / "checkpoint.msgpack").read_bytes() == checkpoint
