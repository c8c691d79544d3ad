"""The whole edit pipeline on a tiny scene with a random-weight model: every stage runs, a rerun
skips finished stages, a changed setting redoes exactly the stages that depend on it, and the
edited dataset is a nerfstudio dataset whose unmasked pixels are the originals."""

import json
import shutil
from pathlib import Path

import gin
import jax
import numpy as np
import pytest

from signerf_jax import camera, checkpoints, configs, files
from signerf_jax.data import load_dataset
from signerf_jax.editing.project import EditDirectory, frame_name
from signerf_jax.editing import commands, stages
from signerf_jax.errors import InputError
from signerf_jax.nerf import render, sampling

pytestmark = pytest.mark.slow

REUSED = "reusing its earlier result"  # What a stage that is not run again says.


def settings_of(chosen: list[str]):
  """The edit's settings from gin bindings, as the commands build them."""
  configs.parse_gin([], chosen)
  return commands.edit_settings()


def bindings(scene_dir: Path, model: Path, scene: dict, **overrides) -> list[str]:
  free_spot = scene["free_spot"]
  values = {
      "EditConfig.data": repr(str(scene_dir)), "EditConfig.prompt": "'a red cow'",
      "EditConfig.model": repr(str(model)), "EditConfig.nerf_update": "'finetune'",
      "SelectionConfig.kind": "'proxy'", "SelectionConfig.proxy": "'primitive:cow'",
      "SelectionConfig.ground_position": repr(tuple(free_spot["center"])),
      "SelectionConfig.ground_size": repr(min(1.6 * free_spot["radius"], 0.3)),
      "SelectionConfig.up": repr(tuple(scene["up"])),
      "SheetConfig.tile_size": "16",
      "original/TrainConfig.steps": "40", "finetune/TrainConfig.steps": "10",
      "first_iteration/GenerationOptions.num_inference_steps": "2",
      "PreviewConfig.seeds": "(0, 1)", "UpdateConfig.views_per_device": "4",
      "EvaluationConfig.independent_views": "2", "EvaluationConfig.video_frames": "0",
      "NerfConsistencySettings.enabled": "True",
      "NerfConsistencySettings.correspondence_size": "48",
      "NerfConsistencySettings.correspondence_views": "3",
      "NerfConsistencySettings.num_resamples": "200",
  }
  values.update(overrides)
  return [f"{name} = {value}" for name, value in values.items()]


@pytest.fixture(scope="module")
def finished_edit(tiny_scene, random_model, tmp_path_factory):
  """An edit run to the end once; returns (directory, log lines, bindings)."""
  scene_dir, _ = tiny_scene
  scene = files.read_json(scene_dir / "scene.json")
  directory = tmp_path_factory.mktemp("edit")
  chosen = bindings(scene_dir, random_model, scene)
  lines = []
  stages.run_edit(directory, settings_of(chosen), progress=False, log=lines.append)
  yield directory, lines, chosen
  gin.clear_config()


def stage_lines(lines, name):
  return [line for line in lines if line.split(":")[0].endswith(f"] {name}")]


def test_every_stage_runs_and_the_evaluation_is_written(finished_edit):
  directory, lines, _ = finished_edit
  for name in ("original", "select", "views", "reference", "preview", "sheet", "update",
               "dataset", "finetune", "evaluate"):
    assert stage_lines(lines, name), name
  # The random model's model_index.json records no growth of its own: the default's is used.
  assert "masks grown 24 px at 512" in stage_lines(lines, "reference")[-1]
  metrics = files.read_json(directory / "evaluation" / "metrics.json")
  assert np.isfinite(metrics["background"]["psnr_paper"])
  assert set(metrics["consistency"]) >= {"original", "sheet_propagated", "independent"}
  assert set(metrics["stage_seconds"]) == {"original", "select", "views", "reference", "preview",
                                           "sheet", "update", "dataset", "finetune", "evaluate"}
  assert (directory / "preview" / "preview.png").is_file()
  assert (directory / "evaluation" / "before_after.png").is_file()


def test_the_evaluation_measures_fit_solidity_and_correspondences_on_the_nerf(finished_edit):
  directory, _, _ = finished_edit
  metrics = files.read_json(directory / "evaluation" / "metrics.json")
  measured = metrics["nerf_consistency"]
  summaries = [measured["fit_psnr"], *measured["solidity"].values()]
  for summary in summaries:
    low, high = summary["interval"]
    assert low <= summary["mean"] <= high and summary["count"] == len(
        [value for value in summary["per_view"] if value is not None])
  assert 0 <= measured["solidity"]["iou"]["mean"] <= 1
  assert 0 <= measured["solidity"]["mean_opacity"]["mean"] <= 1
  correspondences = measured["correspondences"]
  assert correspondences["matcher"] == "tracked"
  assert max(correspondences["size"]) == 48
  assert correspondences["views"] == min(3, metrics["num_eval_views"])
  assert correspondences["pairs"] >= 1
  assert (directory / "evaluation" / "solidity.png").is_file()


def test_the_edited_dataset_keeps_unmasked_pixels_and_records_its_provenance(finished_edit,
                                                                             tiny_scene):
  directory, _, _ = finished_edit
  scene_dir, _ = tiny_scene
  edited = load_dataset(directory / "dataset", split="all")
  original = load_dataset(scene_dir, split="train")
  assert edited.num_images == original.num_images
  masks = np.stack([np.load(path)["mask"] for path in sorted((directory / "views").glob("*.npz"))])
  outside = masks == 0
  # 8-bit PNGs on both sides: outside the mask the edited images are the originals bit for bit.
  np.testing.assert_array_equal(edited.images[outside], original.images[outside])
  assert np.any(np.abs(edited.images - original.images) > 0.05)
  provenance = files.read_json(directory / "dataset" / "transforms.json")["signerf"]["provenance"]
  assert provenance["prompt"] == "a red cow" and provenance["sheet"] == "0"


def region_hits(model, cameras) -> np.ndarray:
  """[N, H, W] bool: the pixels some of whose rays (`Capacity.pixel_samples`^2 of them, as the
  model renders) cross its edit region."""
  hits = np.zeros((cameras.num_cameras, cameras.height, cameras.width), bool)
  for index in range(cameras.num_cameras):
    for position in camera.subpixel_positions(model.capacity.pixel_samples):
      rays = camera.image_rays(cameras, index, position)
      hits[index] |= np.asarray(sampling.intersect_aabb(
          rays.origins, rays.directions, np.asarray(model.edit_region, np.float32))[2])
  return hits


def test_the_edited_nerf_changes_only_the_grown_selection_box(finished_edit):
  directory, lines, chosen = finished_edit
  run = stages.EditContext(EditDirectory(directory), settings_of(chosen), progress=False)
  original, edited = run.nerf(0), run.nerf(1)
  lower, upper = np.asarray(edited.model.edit_region)
  selection_lower, selection_upper = run.selection.bounds
  assert np.all(lower < selection_lower) and np.all(upper > selection_upper)
  assert edited.model.original == original.model
  assert "inside the box" in stage_lines(lines, "finetune")[-1]
  cameras = run.eval_cameras
  before = render.render_cameras(original.model, original.variables, cameras)["rgb"]
  after = render.render_cameras(edited.model, edited.variables, cameras)["rgb"]
  missed = ~region_hits(edited.model, cameras)
  assert missed.any() and not missed.all()
  np.testing.assert_allclose(after[missed], before[missed], atol=1e-6)


def test_a_rerun_skips_finished_stages_and_a_new_sheet_redoes_only_what_follows(finished_edit):
  directory, _, chosen = finished_edit
  lines = []
  stages.run_edit(directory, settings_of(chosen), until="sheet", progress=False,
                  log=lines.append)
  assert all(REUSED in line for line in lines), lines

  lines = []
  stages.run_edit(directory, settings_of(chosen + ["EditConfig.sheet = '0/1@5'"]),
                  until="update", progress=False, log=lines.append)
  redone = {line.split("] ")[1].split(":")[0] for line in lines if REUSED not in line}
  assert redone == {"sheet", "update"}, lines
  sheet = np.load(directory / "sheet" / "sheet.npz")
  assert str(sheet["recipe"]) == "0/1@5"


def test_the_preview_shows_each_candidate_as_soon_as_it_is_made(finished_edit, tmp_path,
                                                                 monkeypatch):
  directory, _, chosen = finished_edit
  directory = Path(shutil.copytree(directory, tmp_path / "edit"))
  widths = []  # Of preview.png, each time it is written.
  write_image = files.write_image

  def recording(path, image, *args, **kwargs):
    if Path(path).name == "preview.png":
      widths.append(np.asarray(image).shape[1])
    return write_image(path, image, *args, **kwargs)

  monkeypatch.setattr(files, "write_image", recording)
  stages.run_edit(directory, settings_of(chosen + ["PreviewConfig.seeds = (1, 3, 4)"]),
                  until="preview", progress=False, log=lambda line: None)
  # Seed 1's candidate was made before; seeds 3 and 4 come one at a time, each shown at once.
  assert len(widths) == 3 and widths[0] < widths[1] == widths[2], widths
  for seed in (1, 3, 4):
    assert (directory / "preview" / "candidates" / f"{seed}.png").is_file()


def test_an_edit_that_runs_the_update_makes_the_preview_with_the_updates_sampler(
    finished_edit, tmp_path):
  """When the update follows in the same process, the preview's candidates go through the
  update's batches and compiled sampler: one sampler compiled for both stages (tiles of a size
  nothing in this process compiled for before)."""
  directory, _, chosen = finished_edit
  directory = Path(shutil.copytree(directory, tmp_path / "edit"))
  compiled = []

  def record(event, duration, **kwargs):
    del duration
    if event.endswith("backend_compile_duration"):
      compiled.append(kwargs.get("fun_name"))

  jax.monitoring.register_event_duration_secs_listener(record)
  try:
    stages.run_edit(directory, settings_of(chosen + ["SheetConfig.tile_size = 24"]),
                    until="update", progress=False, log=lambda line: None)
  finally:
    jax.monitoring.unregister_event_duration_listener(record)
  assert compiled.count("jit(sample)") == 1, compiled
  for seed in (0, 1):
    assert (directory / "preview" / "candidates" / f"{seed}.png").is_file()


def test_an_unknown_stage_is_an_error_naming_the_stages(finished_edit):
  directory, _, chosen = finished_edit
  with pytest.raises(InputError, match="unknown stage 'sheets'.*update"):
    stages.run_edit(directory, settings_of(chosen), until="sheets", progress=False,
                    log=lambda line: None)


def test_without_an_edit_region_the_whole_nerf_is_fine_tuned(finished_edit):
  directory, _, chosen = finished_edit
  # Back to the fixture's edit (earlier tests may change it).
  stages.run_edit(directory, settings_of(chosen), until="finetune", progress=False,
                  log=lambda line: None)
  lines = []
  edit = stages.run_edit(directory, settings_of(chosen + ["FinetuneConfig.edit_region = False"]),
                         until="finetune", progress=False, log=lines.append)
  redone = {line.split("] ")[1].split(":")[0] for line in lines if REUSED not in line}
  assert redone == {"finetune"}, lines
  assert edit.nerf(1).model.edit_region is None


def test_the_reference_views_alone_become_the_edited_dataset(finished_edit, tmp_path):
  """UpdateConfig.propagation = 'reference_views' (a baseline): no view is inpainted; the NeRF
  learns the sheet's tiles at the reference cameras, and the evaluation measures its fit to
  them."""
  directory, _, chosen = finished_edit
  directory = Path(shutil.copytree(directory, tmp_path / "edit"))
  settings = settings_of(chosen + ["UpdateConfig.propagation = 'reference_views'"])
  lines = []
  stages.run_edit(directory, settings, progress=False, log=lines.append)
  redone = {line.split("] ")[1].split(":")[0] for line in lines if REUSED not in line}
  assert redone == {"update", "dataset", "finetune", "evaluate"}, lines
  assert "no view updated" in stage_lines(lines, "update")[-1]
  edited = load_dataset(directory / "dataset", split="all")
  sheet = np.load(directory / "sheet" / "sheet.npz")
  layout = stages.EditContext(EditDirectory(directory), settings).layout
  assert edited.num_images == layout.num_tiles and edited.width == 16
  np.testing.assert_allclose(edited.images[0], sheet["rgb"][:16, :16], atol=1 / 255)
  metrics = files.read_json(directory / "evaluation" / "metrics.json")
  fit = metrics["nerf_consistency"]["fit_psnr"]
  assert len(fit["per_view"]) == layout.num_tiles and np.isfinite(fit["mean"])


def test_a_command_saves_the_bindings_that_a_later_command_reads_back(finished_edit, capsys):
  directory, _, chosen = finished_edit
  settings = settings_of(chosen)
  commands.run_command("edit", directory, progress=False)  # Every stage done before: fast.
  assert REUSED in capsys.readouterr().err
  gin.clear_config()
  commands.parse_edit_config(directory, (), ())  # config.gin only, no bindings given.
  assert commands.edit_settings() == settings


def test_eval_of_an_edit_prints_one_json_line(finished_edit, capsys):
  directory, _, chosen = finished_edit
  settings_of(chosen)
  commands.run_command("edit", directory, progress=False)  # Saves config.gin; all done before.
  capsys.readouterr()
  assert commands.run_evaluation(directory) == 0
  out = capsys.readouterr().out
  assert len(out.splitlines()) == 1, out
  assert np.isfinite(json.loads(out)["background"]["psnr_paper"])


def test_eval_of_an_edit_turns_on_its_costlier_parts_from_gin(finished_edit, tmp_path, capsys):
  directory, _, _ = finished_edit
  assert not (directory / "evaluation" / "before_after.mp4").exists()  # Off by default.
  copy = tmp_path / "edit"
  shutil.copytree(directory, copy)
  assert commands.run_evaluation(copy, (), ["EvaluationConfig.independent_views = 1",
                                            "EvaluationConfig.video_frames = 2"]) == 0
  metrics = json.loads(capsys.readouterr().out)
  assert metrics["independent_edits"]["views"] == 1
  assert (copy / "evaluation" / "before_after.mp4").is_file()


def test_only_the_views_that_show_the_selection_are_inpainted(finished_edit):
  directory, lines, _ = finished_edit
  views = files.read_json(directory / "views" / "views.json")
  shown = [index for index, count in enumerate(views["mask_pixels"]) if count >= 1]
  assert views["visible"] == shown and views["empty"] == sorted(
      set(range(len(views["mask_pixels"]))) - set(shown))
  written = sorted(path.name for path in (directory / "update" / "images").glob("*.png"))
  assert written == [f"{frame_name(index)}.png" for index in shown]
  summary = stage_lines(lines, "update")[-1]
  assert (f"{len(shown)} views inpainted" in summary and
          f"{len(views['empty'])} without the selection left as they are" in summary)


def test_a_time_budgeted_edit_replayed_trains_the_same_nerfs_bit_for_bit(tiny_scene, random_model,
                                                                        tmp_path):
  scene_dir, _ = tiny_scene
  scene = files.read_json(scene_dir / "scene.json")
  budgets = {f"{run}/TrainConfig.{field}": value for run, seconds in (("original", "6.0"),
                                                                     ("finetune", "3.0"))
             for field, value in (("steps", "1000000"), ("max_seconds", seconds))}
  timed = bindings(scene_dir, random_model, scene, **budgets)
  stages.run_edit(tmp_path / "timed", settings_of(timed), until="finetune", progress=False,
                  log=lambda line: None)
  replayed = timed + [f"EditConfig.replay = {str(tmp_path / 'timed')!r}"]
  stages.run_edit(tmp_path / "replayed", settings_of(replayed), until="finetune",
                  progress=False, log=lambda line: None)
  for run in ("original", "edited"):
    first, first_metadata = checkpoints.read(tmp_path / "timed" / run)
    second, second_metadata = checkpoints.read(tmp_path / "replayed" / run)
    assert first_metadata["step"] == second_metadata["step"] >= 1
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second)):
      assert np.array_equal(np.asarray(a), np.asarray(b)), run
