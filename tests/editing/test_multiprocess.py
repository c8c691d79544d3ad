"""Two processes joined through jax.distributed (two local CPU processes, one device each) train
the same NeRF and edit the same images as one process, and only process 0 writes."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

from signerf_jax import checkpoints, files

pytestmark = pytest.mark.slow

STEPS = 12
# Each process, as on a host of its own, sees one CPU device.
ENVIRONMENT = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=1",
               "JAX_PLATFORMS": "cpu"}


def free_port() -> int:
  with socket.socket() as probe:
    probe.bind(("127.0.0.1", 0))
    return probe.getsockname()[1]


def signerf(*argv, processes: int = 1) -> list[subprocess.CompletedProcess]:
  """Runs `signerf ARGV` as one process, or as `processes` joined through a local coordinator."""
  command = [sys.executable, "-m", "signerf_jax.cli", *map(str, argv)]
  if processes == 1:
    return [subprocess.run(command, env=ENVIRONMENT, capture_output=True, text=True,
                           timeout=600, check=False)]
  address = f"127.0.0.1:{free_port()}"
  running = [subprocess.Popen(command + ["--coordinator_address", address, "--num_processes",
                                         str(processes), "--process_id", str(index)],
                              env=ENVIRONMENT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for index in range(processes)]
  finished = []
  for process in running:
    stdout, stderr = process.communicate(timeout=600)
    finished.append(subprocess.CompletedProcess(process.args, process.returncode, stdout,
                                                stderr))
  return finished


def assert_succeeded(done: list[subprocess.CompletedProcess]) -> None:
  for process in done:
    assert process.returncode == 0, process.stderr[-3000:]


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory):
  """The tiny scene trained for STEPS steps by one process and by two."""
  scene_dir, _ = tiny_scene
  root = tmp_path_factory.mktemp("multiprocess")
  runs = {"one": root / "one", "two": root / "two"}
  train = ("train", "--data", scene_dir, "--steps", STEPS, "--skip_eval")
  one = signerf(*train, "--run", runs["one"])
  two = signerf(*train, "--run", runs["two"], processes=2)
  assert_succeeded(one + two)
  return runs, one, two


def test_two_processes_train_the_parameters_one_process_trains(trained):
  runs, _, _ = trained
  one, one_metadata = checkpoints.read(runs["one"])
  two, two_metadata = checkpoints.read(runs["two"])
  assert one_metadata["step"] == two_metadata["step"] == STEPS
  # The batch's sums run over two devices instead of one: the same up to their order, which
  # Adam (eps 1e-15) turns into a difference of up to a share of one step where a gradient is
  # near zero (5 of the grid's 58,992 entries differed by up to 5e-4).
  for a, b in zip(jax.tree.leaves(one["variables"]["params"]),
                  jax.tree.leaves(two["variables"]["params"])):
    np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3)


def test_a_checkpoint_of_two_processes_resumes_in_one(trained, tmp_path):
  runs, _, _ = trained
  resumed = tmp_path / "resumed"
  shutil.copytree(runs["two"], resumed)
  assert_succeeded(signerf("train", "--run", resumed, "--data", files.read_json(
      resumed / "model.json")["data_options"]["root"], "--steps", STEPS + 2, "--skip_eval"))
  assert checkpoints.read(resumed)[1]["step"] == STEPS + 2


def test_only_process_zero_writes_and_prints(trained):
  runs, one, two = trained
  assert sorted(path.name for path in runs["two"].iterdir()) == sorted(
      path.name for path in runs["one"].iterdir())
  # (What the collectives library prints itself, from C++, is not the command's.)
  assert "signerf train:" in two[0].stdout and "signerf" not in two[1].stdout
  assert "step" not in two[1].stderr  # no progress bar


def test_two_processes_edit_the_images_one_process_edits(trained, tiny_scene, random_model,
                                                         tmp_path):
  runs, _, _ = trained
  scene_dir, _ = tiny_scene
  scene = files.read_json(scene_dir / "scene.json")
  free_spot = scene["free_spot"]
  bindings = [
      "EditConfig.prompt = 'a red cow'", f"EditConfig.model = {str(random_model)!r}",
      "SelectionConfig.kind = 'proxy'", "SelectionConfig.proxy = 'primitive:cow'",
      f"SelectionConfig.ground_position = {tuple(free_spot['center'])!r}",
      f"SelectionConfig.ground_size = {min(1.6 * free_spot['radius'], 0.3)!r}",
      f"SelectionConfig.up = {tuple(scene['up'])!r}", "SheetConfig.tile_size = 16",
      "first_iteration/GenerationOptions.num_inference_steps = 2",
      "PreviewConfig.seeds = (0,)", "UpdateConfig.views_per_device = 2"]
  gin_file = tmp_path / "edit.gin"
  gin_file.write_text("\n".join(bindings) + "\n")
  update = ("update", "--run", runs["one"], "--gin_file", gin_file, "--quiet")
  assert_succeeded(signerf(*update, "--edit", tmp_path / "one"))
  assert_succeeded(signerf(*update, "--edit", tmp_path / "two", processes=2))
  names = sorted(path.name for path in (tmp_path / "one" / "update" / "images").iterdir())
  assert names and names == sorted(
      path.name for path in (tmp_path / "two" / "update" / "images").iterdir())
  for name in names:
    one = files.read_image(tmp_path / "one" / "update" / "images" / name)
    two = files.read_image(tmp_path / "two" / "update" / "images" / name)
    assert np.max(np.abs(one - two)) <= 2 / 255, name
