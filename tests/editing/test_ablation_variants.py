"""experiments/ablations.py: every variant binds existing settings and changes the edit, the
baseline is one edit whichever ablation lists it, missing meshes are skipped, and the figure is
drawn whatever the results (one point, equal values, unmeasured numbers)."""

import gin
import numpy as np
import pytest

from signerf_jax import configs
from signerf_jax.editing import commands, demo, stages
from signerf_jax.editing.project import canonical_json

# A scene description as `synthetic_render.generate` writes it (only what the edit bindings read).
SCENE = {"free_spot": {"center": [0.2, -0.3, 0.0], "radius": 0.3}, "up": [0.0, 0.0, 1.0]}


@pytest.fixture(scope="module")
def ablations_module(experiment_script):
  return experiment_script("ablations")


@pytest.fixture(autouse=True)
def clear_gin():
  yield
  gin.clear_config()


def edit_key(tmp_path, variant_bindings, gin_files=("demo", "ablations")):
  """The pipeline key of a variant's edit (what decides whether two edits are the same)."""
  common = demo.edit_bindings(tmp_path / "scene", SCENE, demo.DemoSettings(), "a red cow",
                              str(tmp_path / "model"))
  common.append(f"EditConfig.original_run = {str(tmp_path / 'nerf')!r}")
  configs.parse_gin(list(gin_files), common + list(variant_bindings))
  return canonical_json(stages.edit_key(tmp_path / "edit", commands.edit_settings()))


@pytest.mark.parametrize("gin_files", [("demo", "ablations"),
                                       ("demo", "ablations", "ablations_smoke")])
def test_every_variant_binds_existing_settings_and_changes_the_edit(ablations_module, tmp_path,
                                                                    gin_files):
  configs.parse_gin(list(gin_files))
  config = ablations_module.AblationConfig()
  for name, ablation in ablations_module.ablations(config).items():
    keys = [edit_key(tmp_path, variant.bindings, gin_files)
            for variant in ablation.variants]
    assert len(set(keys)) == len(keys), name
    # (Without ../shared/data the spot proxies are skipped, not run.)
    assert len(keys) + len(ablation.skipped) >= (1 if name == "propagation" else 2), name


def test_the_baseline_is_one_edit_whichever_ablation_lists_it(ablations_module, tmp_path):
  configs.parse_gin(["demo", "ablations"])
  by_name = {name: {variant.name: variant for variant in ablation.variants} for name, ablation
             in ablations_module.ablations(ablations_module.AblationConfig()).items()}
  baselines = [by_name["propagation"]["baseline"], by_name["controlnet_scale"]["scale_1"],
               by_name["sheet_layout"]["2x3"], by_name["crops"]["crops"],
               by_name["nerf_update"]["retrain_region"]]
  keys = {edit_key(tmp_path, variant.bindings) for variant in baselines}
  assert len(keys) == 1
  assert edit_key(tmp_path, by_name["crops"]["full_frames"].bindings) not in keys


def test_a_missing_proxy_mesh_is_skipped_and_named(ablations_module, tmp_path):
  missing = str(tmp_path / "no_such_cow.obj")
  ablation = ablations_module.ablations(ablations_module.AblationConfig(
      proxies=(missing, "primitive:cow")))["proxy"]
  assert [variant.name for variant in ablation.variants] == ["primitive_cow"]
  assert ablation.skipped == [{"name": "no_such_cow", "missing": missing}]


def variant(name, seconds, **quality):
  keys = ("background_psnr", "consistency_change", "prompt_color_share", "shape_iou",
          "solidity_iou", "solidity_opacity")
  return {"name": name, "edit_seconds": seconds, "quality": {key: quality.get(key)
                                                             for key in keys}}


def test_the_figure_has_a_row_per_ablation_whatever_the_numbers(ablations_module):
  results = {
      "controlnet_scale": {"variants": [
          variant("scale_0.4", 100.0, background_psnr=36.0, consistency_change=-0.3,
                  prompt_color_share=0.5, shape_iou=0.0),
          variant("scale_1", 120.0, background_psnr=37.5, consistency_change=-0.1,
                  prompt_color_share=0.5, shape_iou=0.0)]},
      "proxy": {"variants": [variant("primitive_cow", 90.0, background_psnr=35.0)]},
      "propagation": {"points": [
          {"name": "sheet_propagated", "seconds_per_view": 3.0, "consistency_change": -0.15},
          {"name": "independent", "seconds_per_view": None, "consistency_change": None}]},
  }
  figure = ablations_module.ablation_figure(results)
  panels = len(ablations_module.QUALITY_PANELS)
  assert figure.shape == (3 * ablations_module.PANEL_HEIGHT,
                          panels * ablations_module.PANEL_WIDTH, 3)
  assert figure.dtype == np.uint8
  # The first row has two charts (distinct values) with coloured points, not blank notes.
  first_row = figure[:ablations_module.PANEL_HEIGHT, :2 * ablations_module.PANEL_WIDTH]
  assert np.any(np.ptp(first_row.astype(int), axis=-1) > 100)


@pytest.mark.parametrize("second_iteration", [False, True])
def test_second_iteration_settings_change_the_edit_only_when_it_runs(ablations_module, tmp_path,
                                                                   second_iteration):
  enabled = [f"EditConfig.second_iteration = {second_iteration}"]
  steps = ["second_iteration/GenerationOptions.num_inference_steps = 7"]
  changed = edit_key(tmp_path, enabled) != edit_key(tmp_path, enabled + steps)
  assert changed == second_iteration
