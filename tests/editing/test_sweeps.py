"""editing.commands.sweeps on the tiny scene with a random-weight model: the original NeRF is
trained once and reused, an edit listed twice runs once, and a run is summarised as quality and
time."""

import math

import gin
import pytest

from signerf_jax import files
from signerf_jax.editing.commands import sweeps

from test_pipeline import bindings

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def swept(tiny_scene, random_model, tmp_path_factory):
  """A sweep with its original NeRF trained, the baseline run, and the baseline listed again
  (with a binding that changes nothing); returns (sweep, the two results, log lines)."""
  scene_dir, _ = tiny_scene
  scene = files.read_json(scene_dir / "scene.json")
  lines = []
  sweep = sweeps.Sweep(tmp_path_factory.mktemp("sweep"), [],
                       bindings(scene_dir, random_model, scene), progress=False,
                       log=lines.append)
  original = sweep.train_original()
  first = sweep.run("group", sweeps.Variant("baseline"))
  again = sweep.run("other", sweeps.Variant("crops", ("SheetConfig.crops = True",)))
  yield sweep, original, first, again, lines
  gin.clear_config()


def test_the_original_nerf_is_trained_once_and_reused(swept):
  sweep, original, first, _, lines = swept
  assert (sweep.root / "original" / "original").is_dir() and original["seconds"] > 0
  assert not (sweep.root / "group" / "baseline" / "original").exists()
  used = [line for line in lines if line.startswith("group/baseline") and "] original:" in line]
  assert any("using the trained NeRF" in line for line in used), used
  # With a trained NeRF given, the stage says it loads it (issue 18: it said "training").
  assert not any("training the original NeRF" in line for line in used), used
  assert any("loading the given trained NeRF" in line for line in used), used
  assert first["stage_seconds"]["original"] < original["seconds"]


def test_the_same_edit_listed_twice_runs_once(swept):
  sweep, _, first, again, lines = swept
  assert again["same_as"] == first["directory"] == str(sweep.root / "group" / "baseline")
  assert not (sweep.root / "other").exists()
  assert again["name"] == "crops" and again["bindings"] == ["SheetConfig.crops = True"]
  assert again["quality"] == first["quality"]
  assert not any(line.startswith("other/full_frames [") for line in lines)


def test_a_run_is_summarised_as_quality_and_time(swept):
  _, _, first, _, _ = swept
  stages = first["stage_seconds"]
  assert set(stages) >= {"original", "views", "update", "finetune", "evaluate"}
  assert math.isclose(first["edit_seconds"], sum(stages.values()) - stages["original"]
                      - stages["evaluate"])
  quality = first["quality"]
  assert math.isfinite(quality["background_psnr"]) and 0 <= quality["shape_iou"] <= 1
  assert 0 <= quality["edited_images_shape_iou"] <= 1
  assert quality["clip_directional_similarity"] is None  # no CLIP weights given
  per_view = first["seconds_per_view"]
  assert per_view["sheet_propagated"] > 0 and per_view["independent"] > 0
  assert first["edited_views"] > 0


def test_edit_quality_leaves_out_what_was_not_measured():
  quality = sweeps.edit_quality({"background": {"psnr_paper": 36.5, "ssim_paper": 0.99},
                                 "prompt_color_adherence": {"image_set": None,
                                                            "nerf_renders": None}})
  assert quality["background_psnr"] == 36.5 and quality["background_ssim"] == 0.99
  assert all(quality[name] is None for name in quality
             if name not in ("background_psnr", "background_ssim"))


def test_edit_quality_reports_the_edited_nerfs_fit_and_solidity():
  quality = sweeps.edit_quality({"nerf_consistency": {
      "fit_psnr": {"mean": 29.0, "interval": [28.5, 29.5]},
      "solidity": {"iou": {"mean": 0.81}, "mean_opacity": {"mean": 0.93}}},
      "shape_iou": {"image_set": 0.72, "nerf_renders": 0.68}})
  assert (quality["fit_psnr"], quality["solidity_iou"], quality["solidity_opacity"]) == (
      29.0, 0.81, 0.93)
  assert (quality["edited_images_shape_iou"], quality["shape_iou"]) == (0.72, 0.68)
