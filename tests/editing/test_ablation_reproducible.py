"""experiments/ablations.py trains its NeRFs for step counts, so a rerun reproduces its numbers:
the smoke ablation's baseline (`--only controlnet_scale` at the baseline's scale alone: about a
minute a run on a 2-core CPU), run twice into two folders, gives the same JSON but for the
timings; and
the JSON records the code's commit, the gin settings and every seed."""

import json
from pathlib import Path

import gin
import pytest

# Parts of a key that mark a timing or the machine's state: the only fields two runs may differ in.
TIMING_KEY_PARTS = ("seconds", "date", "load_average", "machine")


def without_timings(value):
  """`value` (parsed JSON) without the fields whose key names a timing."""
  if isinstance(value, dict):
    return {key: without_timings(item) for key, item in value.items()
            if not any(part in key for part in TIMING_KEY_PARTS)}
  if isinstance(value, list):
    return [without_timings(item) for item in value]
  return value


def run_smoke_ablation(script, folder: Path) -> dict:
  """Runs the smoke ablation's baseline into `folder`; its ablations.json with `folder` written
  as FOLDER (the runs' paths differ by it alone)."""
  code = script.main(["--smoke", "--only", "controlnet_scale", "--quiet",
                      "--gin_param", "ablations.controlnet_scales = (1.0,)",
                      "--out", str(folder / "edits"), "--results", str(folder / "results")])
  assert code == 0
  text = (folder / "results" / "ablations.json").read_text()
  return json.loads(text.replace(str(folder.resolve()), "FOLDER").replace(str(folder), "FOLDER"))


@pytest.mark.slow
def test_the_smoke_ablation_run_twice_gives_the_same_numbers(experiment_script, tmp_path):
  script = experiment_script("ablations")
  try:
    first, second = (run_smoke_ablation(script, tmp_path / name) for name in ("first", "second"))
  finally:
    gin.clear_config()
  assert first["machine"]["commit"] is not None
  assert "original/TrainConfig.steps = 60" in first["gin_config"]
  assert "original/TrainConfig.max_seconds = None" in first["gin_config"]
  assert first["seeds"]["edit.training.original.seed"] == 0
  variants = first["ablations"]["controlnet_scale"]["variants"]
  assert [variant["name"] for variant in variants] == ["scale_1"]
  assert without_timings(first) == without_timings(second)
