import json

import numpy as np
import pytest

from signerf_jax import cli, files
from signerf_jax.data import write_nerfstudio

GIN_PARAMS = ["--gin_param", "CapacityRules.rays_per_batch = 512",
              "--gin_param", "CapacityRules.samples_per_batch = 4096",
              "--gin_param", "TrainConfig.occupancy_warmup_steps = 4",
              "--gin_param", "TrainConfig.occupancy_update_every = 4"]


@pytest.fixture(scope="module")
def scene_dir(sphere, tmp_path_factory):
  directory = tmp_path_factory.mktemp("sphere_scene")
  write_nerfstudio(directory, sphere)
  return directory


@pytest.mark.slow
def test_train_resume_eval_and_render(scene_dir, tmp_path, capsys):
  run = tmp_path / "run"
  assert cli.main(["train", "--data", str(scene_dir), "--run", str(run), "--steps", "6",
                   *GIN_PARAMS]) == 0
  assert "6 steps" in capsys.readouterr().out
  config = (run / "config.gin").read_text()
  assert "CapacityRules.samples_per_batch = 4096" in config and "TrainConfig" in config
  # Resuming with more steps continues from the checkpoint with the run's own configuration.
  assert cli.main(["train", "--data", str(scene_dir), "--run", str(run), "--steps", "9"]) == 0
  assert "9 steps" in capsys.readouterr().out

  assert cli.main(["eval", "--run", str(run)]) == 0
  result = json.loads(capsys.readouterr().out)  # Exactly one JSON line on stdout.
  held_out = result["held_out"]
  assert {"psnr", "ssim", "depth_mae", "near_camera_weight"} <= set(held_out)
  assert held_out["depth_mae"] is not None and result["seconds_trained"] > 0
  assert result["generalisation_gap_db"] == pytest.approx(
      result["train"]["psnr"] - held_out["psnr"])
  assert files.read_json(run / "eval.json") == result
  # Every held-out view's render and depth map, as pictures.
  assert len(list((run / "eval").glob("*.depth.png"))) == held_out["num_views"]
  # 14 training views: a sparse capture, evaluated as trained, 2 x 2 rays a pixel; one ray
  # through each pixel's centre when asked.
  assert cli.main(["eval", "--run", str(run), "--supersampling", "1"]) == 0
  centre = json.loads(capsys.readouterr().out)["held_out"]
  assert held_out["supersampling"] == 2 and centre["supersampling"] == 1
  assert centre["psnr"] != held_out["psnr"]

  out = tmp_path / "renders"
  assert cli.main(["render", "--run", str(run), "--out", str(out), "--video",
                   "--frames", "3"]) == 0
  pngs = sorted((out / "eval").glob("*.png"))
  exrs = sorted((out / "eval").glob("*.depth.exr"))
  assert len(exrs) == held_out["num_views"] and len(pngs) == 3 * len(exrs)
  depth = files.read_exr(exrs[0])
  assert depth.shape == (24, 24) and np.all(np.isfinite(depth))
  video = [path for path in out.iterdir() if path.stem == "video"]
  assert len(video) == 1 and video[0].stat().st_size > 0

  # `signerf info`: one JSON line on stdout, the same in words on stderr.
  capsys.readouterr()
  assert cli.main(["info", "--run", str(run)]) == 0
  captured = capsys.readouterr()
  info = json.loads(captured.out)
  assert info["views"]["count"] == 14 and info["views"]["width"] == 24
  assert info["frame"]["kind"] == "bounded" and info["default_proxy_size"] > 0
  assert "signerf info: 14 training views of 24x24 px" in captured.err


def test_eval_of_a_missing_run_is_an_input_error(tmp_path, capsys):
  assert cli.main(["eval", "--run", str(tmp_path / "nothing")]) == 2
  assert "nothing" in capsys.readouterr().err
