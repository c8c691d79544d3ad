"""3D consistency measured on the edited NeRF: sheet propagation against independent edits.

    python experiments/nerf_consistency.py [--scenes demo stitch]
        [--arms independent reference_views] [--out DIR] [--results DIR] [--stitch_edit EDIT]
        [--smoke] [--gin_file F] [--gin_param P]

The paper's claim (Sec. 3 and its appendix): views updated through the reference sheet agree, so
the NeRF fitted to them holds a solid object, while views inpainted each on its own disagree and
are averaged into a haze. For each scene the same edit runs with the image set updated through
the sheet ("sheet", `UpdateConfig.propagation = 'sheet'`, the method), each view inpainted on
its own ("independent", the paper's baseline) and no view updated, the NeRF learning the sheet's
tiles at the reference cameras alone ("reference_views": what the update adds), sharing one
original NeRF (`editing.commands.sweeps`).
Each edit's evaluation measures the edited NeRF (`NerfConsistencySettings`, switched on by
gin_configs/nerf_consistency.gin; `editing.stages.nerf_consistency`): fit PSNR against its own
training images inside the selection, solidity (IoU of opacity > 0.5 with the proxy's silhouette
and the mean opacity inside it, at held-out cameras) and verified correspondences between
256-px renders of neighbouring held-out cameras, each with a 95% bootstrap interval.

Scenes:
  demo    `signerf demo`'s scene and edit (gin_configs/demo.gin): a cow on a generated scene;
  stitch  the real 360-degree capture, edited as experiments/real_scene_edit.py left it in
          --stitch_edit (its config.gin: the trained NeRF and the teddy bear placed with
          `signerf place`), every NeRF training of the edit under 120 s, no orbit video.

Writes into --results DIR (default outputs/experiments/) nerf_consistency.json (per scene and
arm: the measurements, the edit's headline quality and seconds; per other arm and measurement,
whether the sheet's interval lies wholly above the arm's, "higher", wholly below, "lower", or
neither, "overlapping"; and per other arm and per-view measurement, the interval of the
view-by-view difference, "significant" when it leaves out zero) and nerf_consistency.png (the
intervals, and each arm's before/after held-out renders). --smoke adds
gin_configs/nerf_consistency_smoke.gin (tiny budgets, numbers meaningless).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import configs, files
from signerf_jax.editing import commands, demo, figures
from signerf_jax.editing.commands import sweeps
from signerf_jax.editing.commands.sweeps import Variant
from signerf_jax.errors import InputError
from signerf_jax.metrics import solidity

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

ARMS = (Variant("sheet"), Variant("independent", ("UpdateConfig.propagation = 'independent'",)),
        Variant("reference_views", ("UpdateConfig.propagation = 'reference_views'",)))
# Every NeRF training of a stitch edit under 120 s, as real_scene_edit.py's; no orbit video (the
# measurements do not use it, and at 200 px it is 96 renders, about 4 minutes per arm).
STITCH_SETTINGS = ("finetune/TrainConfig.max_seconds = 120.0",
                   "retrain/TrainConfig.max_seconds = 120.0", "EvaluationConfig.video_frames = 0")
# (key in the measurements, figure title, unit), each summarised with an interval.
MEASURES = (("fit_psnr", "fit PSNR inside the selection", "dB"),
            ("solidity/iou", "solidity: IoU of opacity > 0.5", "IoU"),
            ("solidity/mean_opacity", "solidity: opacity in the silhouette", "opacity"),
            ("correspondences", "correspondences vs original", "relative change"))
# The measures taken view by view, compared view by view (correspondences are counted per pair
# of views and compared through their relative change). Solidity is measured at the held-out
# cameras in every arm; fit at the views each arm's NeRF learned: the dataset's views, but for
# "reference_views" the reference cameras, so its fit is not paired with the sheet's.
PER_VIEW_MEASURES = ("fit_psnr", "solidity/iou", "solidity/mean_opacity")
FIT_AT_OTHER_VIEWS = ("reference_views",)


def _measure(measured: dict[str, Any], key: str) -> dict[str, Any]:
  """A measurement's summary {mean, interval} by its MEASURES key."""
  if key == "correspondences":
    value = measured["correspondences"]
    return {"mean": value["relative_change"], "interval": value["interval"]}
  for name in key.split("/"):
    measured = measured[name]
  return measured


def scene_sweep(scene: str, out: Path, gin_files: list[str], gin_params: list[str],
                stitch_edit: Path, progress: bool) -> sweeps.Sweep:
  log = lambda line: print(f"nerf_consistency {scene}: {line}", flush=True)
  if scene == "demo":
    configs.parse_gin(["demo", *gin_files], gin_params)
    settings = configs.build(demo.DemoSettings)
    scene_json = demo.ensure_scene(out / "scene", settings.scene_seed)
    bindings = demo.edit_bindings(out / "scene", scene_json, settings, settings.prompt,
                                  demo.model_directory(None))
    return sweeps.Sweep(out, ["demo", *gin_files], bindings + gin_params, progress, log)
  placed = stitch_edit / "config.gin"
  if not placed.is_file():
    raise InputError("no placed edit here: run experiments/real_scene_edit.py first", placed)
  bindings = ["EditConfig.prompt = 'a red teddy bear'", *STITCH_SETTINGS]
  return sweeps.Sweep(out, [str(placed), *gin_files], bindings + gin_params, progress, log)


def chosen_arms(baselines: list[str]) -> tuple[Variant, ...]:
  """The sheet's arm and the named baselines (`ARMS`'s names), in `ARMS`'s order."""
  return tuple(arm for arm in ARMS if arm.name == "sheet" or arm.name in baselines)


def run_scene(sweep: sweeps.Sweep, arms: tuple[Variant, ...]) -> dict[str, Any]:
  """The arms of one scene (the sheet's first): each arm's measurements, quality and seconds,
  and how the sheet's intervals lie against each other arm's."""
  result: dict[str, Any] = {"original_nerf": sweep.train_original(), "arms": {}}
  for arm in arms:
    summary = sweep.run("arms", arm)
    metrics = files.read_json(Path(summary["directory"]) / "evaluation" / "metrics.json")
    result["arms"][arm.name] = {"bindings": list(arm.bindings),
                                "directory": summary["directory"],
                                "nerf_consistency": metrics["nerf_consistency"],
                                "quality": summary["quality"],
                                "edit_seconds": summary["edit_seconds"]}
  result.update(compare_arms(result["arms"]))
  return result


def compare_arms(arms: dict[str, Any]) -> dict[str, Any]:
  """How the sheet's measurements lie against each other arm's (every measure is better
  higher; the paper expects the sheet higher).

  Args:
    arms: per arm name (the sheet's "sheet"), {"nerf_consistency": the edit's measurements}.
  Returns:
    sheet_against: per baseline and measure, the sheet's interval "higher" than the
      baseline's, "lower", or "overlapping";
    sheet_minus: per baseline and per-view measure (`PER_VIEW_MEASURES`) both measured at the
      same views (not the fit of `FIT_AT_OTHER_VIEWS`), the view-by-view difference sheet -
      baseline (`solidity.paired_difference`: the spread from view to view cancels).
  """
  sheet = arms["sheet"]["nerf_consistency"]
  baselines = {name: arm["nerf_consistency"] for name, arm in arms.items() if name != "sheet"}
  paired = lambda name: [key for key in PER_VIEW_MEASURES
                         if not (key == "fit_psnr" and name in FIT_AT_OTHER_VIEWS)]
  return {
      "sheet_against": {name: {key: solidity.compare(_measure(sheet, key), _measure(other, key))
                               for key, _, _ in MEASURES} for name, other in baselines.items()},
      "sheet_minus": {name: {key: solidity.paired_difference(_measure(sheet, key)["per_view"],
                                                             _measure(other, key)["per_view"])
                             for key in paired(name)} for name, other in baselines.items()}}


def figure(results: dict[str, Any]) -> np.ndarray:
  """[H, W, 3] float32 RGB: per scene, the intervals of every measure, then each arm's
  before/after held-out renders."""
  rows = []
  for scene, result in results.items():
    arms = result["arms"]
    panels = [plotting.interval_chart(f"{scene}: {title}", [
        (name, _measure(arm["nerf_consistency"], key)["mean"],
         *(_measure(arm["nerf_consistency"], key)["interval"] or (None, None)))
        for name, arm in arms.items()], unit) for key, title, unit in MEASURES]
    rows.append(plotting.side_by_side(panels))
    for name, arm in arms.items():
      image = files.read_image(Path(arm["directory"]) / "evaluation" / "before_after.png")
      rows.append(figures.image_grid([[image[..., :3]]], [[f"{scene}, {name}: before / after"]]))
  return plotting.stacked(rows)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scenes", nargs="+", choices=("demo", "stitch"), default=["demo"])
  parser.add_argument("--arms", nargs="+", choices=[arm.name for arm in ARMS[1:]],
                      default=[arm.name for arm in ARMS[1:]],
                      help="the arms compared with the sheet (which always runs)")
  parser.add_argument("--out", default="outputs/nerf_consistency", help="the edits (resumed)")
  results_dir.add_argument(parser)
  parser.add_argument("--stitch_edit", default="outputs/real_scene_edit/edit",
                      help="experiments/real_scene_edit.py's edit (its placement)")
  parser.add_argument("--smoke", action="store_true", help="tiny budgets, numbers meaningless")
  commands.add_common_arguments(parser)
  args = parser.parse_args(argv)
  start = time.perf_counter()
  gin_files = ["nerf_consistency", *(["nerf_consistency_smoke"] if args.smoke else []),
               *args.gin_file]
  results, measured_on = {}, machine.record()
  try:
    for scene in args.scenes:
      sweep = scene_sweep(scene, Path(args.out) / scene, gin_files, args.gin_param,
                          Path(args.stitch_edit), not args.quiet)
      results[scene] = run_scene(sweep, chosen_arms(args.arms))
  except InputError as error:
    print(f"nerf_consistency: error: {error}", file=sys.stderr)
    return 2
  output = Path(args.results) / "nerf_consistency.json"
  files.write_json(output, {"machine": measured_on, "gin_files": gin_files, "scenes": results,
                            "seconds": time.perf_counter() - start})
  files.write_image(output.with_suffix(".png"), figure(results))
  print(f"nerf_consistency: {', '.join(args.scenes)} in {time.perf_counter() - start:.0f} s -> "
        f"{output}, {output.with_suffix('.png')}; the sheet against each baseline: "
        + "; ".join(f"{scene} {result['sheet_against']}" for scene, result in results.items()))
  return 0


if __name__ == "__main__":
  sys.exit(main())
