"""The edited-NeRF measurements' geometry (`editing.stages.nerf_consistency`) and the experiment
comparing sheet propagation with independent edits (experiments/nerf_consistency.py): its arms
are distinct edits that measure the NeRF, and its figure is drawn whatever the numbers."""

import gin
import numpy as np
import pytest

from signerf_jax import camera, configs, files
from signerf_jax.editing import commands, demo, stages
from signerf_jax.editing.project import canonical_json
from signerf_jax.editing.stages import nerf_consistency
from signerf_jax.metrics import solidity

selection_rectangles = nerf_consistency._selection_rectangles  # pylint: disable=protected-access


@pytest.fixture(autouse=True)
def clear_gin():
  yield
  gin.clear_config()


@pytest.fixture(scope="module")
def experiment(experiment_script):
  return experiment_script("nerf_consistency")


# Per-view deviations spanning 0.1 with a mean of zero, the same in every arm: an IoU's spread
# from view to view (a fit PSNR's is 10 times it, in dB).
VIEW_SPREAD = np.linspace(-0.05, 0.05, 12)


def measurement(per_view: np.ndarray) -> dict:
  """A stored measurement as an edit's evaluation writes it: summary and per-view values."""
  return {**solidity.summarize(per_view), "per_view": [float(value) for value in per_view]}


@pytest.mark.parametrize("up, low, high", [((0, 0, 1), [0, 0, 0.1], [1, 1, 2]),
                                           ((0, 0, -1), [0, 0, 0], [1, 1, 1.9]),
                                           ((0.1, 0.9, 0.2), [0, 0.05, 0], [1, 1, 2])])
def test_the_opacity_box_leaves_out_the_bottom_along_the_up_axis(up, low, high):
  bounds = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 2.0]])
  box = nerf_consistency.opacity_box(bounds, np.asarray(up, float), 0.05)
  np.testing.assert_allclose(box, [low, high])


def test_selection_rectangles_frame_the_projection_and_ignore_cameras_behind():
  eyes = np.array([[0.0, -3.0, 0.0], [0.0, 3.0, 0.0]], np.float32)
  camera_to_world = np.asarray(camera.look_at(eyes, np.zeros(3, np.float32)))
  cameras = camera.Cameras.create(camera_to_world, fx=20.0, width=32, height=32)
  points = np.array([[-0.3, 0.0, -0.3], [0.3, 0.0, 0.3]])
  rectangles = selection_rectangles(cameras, points)
  assert rectangles.shape == (2, 32, 32)
  for rectangle in rectangles:  # Centred, about 2 * 20 * 0.3 / 3 = 4 px wide.
    rows, columns = np.nonzero(rectangle)
    assert 13 <= columns.min() <= columns.max() <= 18 and 13 <= rows.min() <= rows.max() <= 18
  behind = camera.Cameras.create(np.asarray(camera.look_at(eyes[:1], np.array(
      [0.0, -6.0, 0.0], np.float32))), fx=20.0, width=32, height=32)
  assert not selection_rectangles(behind, points).any()


def test_the_arms_are_distinct_edits_that_measure_the_nerf(experiment, tmp_path):
  scene = {"free_spot": {"center": [0.2, -0.3, 0.0], "radius": 0.3}, "up": [0.0, 0.0, 1.0]}
  common = demo.edit_bindings(tmp_path / "scene", scene, demo.DemoSettings(), "a red cow",
                              str(tmp_path / "model"))
  common.append(f"EditConfig.original_run = {str(tmp_path / 'nerf')!r}")
  keys = []
  for arm in experiment.ARMS:
    configs.parse_gin(["demo", "nerf_consistency"], common + list(arm.bindings))
    settings = commands.edit_settings()
    assert settings.nerf_consistency.enabled
    keys.append(canonical_json(stages.edit_key(tmp_path / arm.name, settings)))
  assert len(set(keys)) == len(experiment.ARMS)


def test_the_figure_is_drawn_whatever_the_numbers(experiment, tmp_path):
  files.write_image(tmp_path / "evaluation" / "before_after.png", np.zeros((8, 16, 3)))
  summary = {"mean": 0.5, "interval": [0.4, 0.6]}
  unmeasured = {"mean": None, "interval": None}
  measured = {"fit_psnr": summary, "solidity": {"iou": summary, "mean_opacity": unmeasured},
              "correspondences": {"relative_change": -0.2, "interval": [-0.2, -0.2]}}
  arms = {name: {"directory": str(tmp_path), "nerf_consistency": measured}
          for name in ("sheet", "independent", "reference_views")}
  image = experiment.figure({"demo": {"arms": arms}})
  assert image.ndim == 3 and image.shape[2] == 3 and np.isfinite(image).all()


def test_a_scene_runs_the_sheet_and_the_chosen_baselines_only(experiment, tmp_path):
  ran = []

  class RecordingSweep:
    """Writes each arm's measurements where an edit's evaluation would."""

    def train_original(self):
      return {"run": str(tmp_path / "nerf"), "seconds": 0.0}

    def run(self, group, arm):
      ran.append(arm.name)
      fit = {"sheet": 20.0, "independent": 18.0}[arm.name]
      iou = {"sheet": 0.7, "independent": 0.8}[arm.name]  # The independent edit's is higher.
      measured = {"fit_psnr": measurement(fit + 10 * VIEW_SPREAD),
                  "solidity": {"iou": measurement(iou + VIEW_SPREAD),
                               "mean_opacity": measurement(fit + 10 * VIEW_SPREAD)},
                  "correspondences": {"relative_change": -0.2, "interval": [-0.3, -0.1]}}
      directory = tmp_path / group / arm.name
      files.write_json(directory / "evaluation" / "metrics.json",
                       {"nerf_consistency": measured})
      return {"directory": str(directory), "quality": {}, "edit_seconds": 1.0}

  result = experiment.run_scene(RecordingSweep(), experiment.chosen_arms(["independent"]))
  assert ran == ["sheet", "independent"] and list(result["arms"]) == ran
  assert result["sheet_against"] == {"independent": {
      "fit_psnr": "higher", "solidity/iou": "lower", "solidity/mean_opacity": "higher",
      "correspondences": "overlapping"}}
  differences = result["sheet_minus"]["independent"]
  assert list(differences) == list(experiment.PER_VIEW_MEASURES)
  assert differences["fit_psnr"]["mean"] == pytest.approx(2.0)
  assert differences["solidity/iou"]["mean"] == pytest.approx(-0.1)
  assert all(difference["significant"] for difference in differences.values())


def test_arms_are_paired_view_by_view_but_for_the_reference_views_fit(experiment):
  """The sheet 0.01 above at every view, views spread by 0.1: the arms' intervals overlap, the
  view-by-view difference lies above zero. The reference views' fit, at other views, is not
  paired."""
  iou = lambda offset: {"fit_psnr": measurement(20.0 + 10 * VIEW_SPREAD),
                        "solidity": {"iou": measurement(0.7 + offset + VIEW_SPREAD),
                                     "mean_opacity": measurement(0.9 + VIEW_SPREAD)},
                        "correspondences": {"relative_change": 0.0, "interval": [0.0, 0.0]}}
  # The reference views' NeRF learned 3 views (the reference cameras).
  reference_views = dict(iou(0.0), fit_psnr=measurement(np.array([20.0, 21.0, 22.0])))
  compared = experiment.compare_arms({"sheet": {"nerf_consistency": iou(0.01)},
                                      "independent": {"nerf_consistency": iou(0.0)},
                                      "reference_views": {"nerf_consistency": reference_views}})
  assert compared["sheet_against"]["independent"]["solidity/iou"] == "overlapping"
  difference = compared["sheet_minus"]["independent"]["solidity/iou"]
  assert difference["significant"] and difference["mean"] == pytest.approx(0.01)
  assert not compared["sheet_minus"]["independent"]["fit_psnr"]["significant"]
  assert list(compared["sheet_minus"]["reference_views"]) == ["solidity/iou",
                                                              "solidity/mean_opacity"]


def test_runs_are_tallied_per_setting_and_a_run_without_per_view_values_is_refused(
    experiment_script, tmp_path, capsys):
  runs_script = experiment_script("nerf_consistency_runs")
  arms = lambda lead: {"sheet": {"nerf_consistency": {
      "fit_psnr": measurement(20.0 + lead + 10 * VIEW_SPREAD),
      "solidity": {"iou": measurement(0.8 + lead / 10 + VIEW_SPREAD),
                   "mean_opacity": measurement(0.9 + VIEW_SPREAD)},
      "correspondences": {"relative_change": 0.0, "interval": [0.0, 0.0]}}},
      "independent": {"nerf_consistency": {
          "fit_psnr": measurement(20.0 + 10 * VIEW_SPREAD),
          "solidity": {"iou": measurement(0.8 + VIEW_SPREAD),
                       "mean_opacity": measurement(0.9 + VIEW_SPREAD)},
          "correspondences": {"relative_change": 0.0, "interval": [0.0, 0.0]}}}}
  paths = []
  for number, lead in enumerate([1.0, 1.0, -1.0]):
    paths.append(str(tmp_path / f"run{number}.json"))
    files.write_json(paths[-1], {"scenes": {"demo": {"arms": arms(lead)}}})
  output = tmp_path / "runs.json"
  assert runs_script.main(["--setting", "demo", *paths, "--output", str(output)]) == 0
  tally = files.read_json(output)["settings"]["demo"]["tally"]["demo"]["independent"]
  assert tally["fit_psnr"] == {"runs": 3, "unpaired": {"higher": 2, "lower": 1},
                               "paired": {"higher": 2, "lower": 1}}
  # The same opacity in both arms: never significant either way.
  assert tally["solidity/mean_opacity"]["paired"] == {"higher": 0, "lower": 0}
  assert files.read_image(output.with_suffix(".png")).ndim == 3
  files.write_json(tmp_path / "old.json", {"scenes": {"demo": {"arms": {
      name: {"nerf_consistency": {"fit_psnr": {"mean": 1.0, "interval": [0.9, 1.1]}}}
      for name in ("sheet", "independent")}}}})
  assert runs_script.main(["--setting", "old", str(tmp_path / "old.json"),
                           "--output", str(output)]) == 2
  assert "old.json" in capsys.readouterr().err
  unpaired = arms(1.0)
  unpaired["independent"]["nerf_consistency"]["fit_psnr"] = measurement(np.array([20.0, 21.0]))
  files.write_json(tmp_path / "unpaired.json", {"scenes": {"demo": {"arms": unpaired}}})
  assert runs_script.main(["--setting", "unpaired", str(tmp_path / "unpaired.json"),
                           "--output", str(output)]) == 2
  assert "unpaired.json: per_view: (12,) and (2,) views" in capsys.readouterr().err
