"""A real-scene edit end to end, as a user runs it: the 360-degree phone capture
../shared/data/stitch (a toy on a table, the room behind), a teddy-bear mesh from
../shared/data/meshes placed on the table with `signerf place`, the preview, the edit and its
evaluation with the shipped model.

  python experiments/real_scene_edit.py [--out outputs/real_scene_edit] [--train_seconds 300]
      [--edit_seconds 120]

Every step is the `signerf` command a user types, each in a process of its own, all sharing one
compilation cache that starts empty (OUT/compilation_cache; the NeRF is reused when OUT/run
exists, and then its command only resumes and evaluates: the NeRF's own training seconds are
recorded apart): train (time budget `--train_seconds`), info, place (a view, a pixel on the
table in front of the toy), preview (four candidate sheets, the inpainting masks grown by the
shipped model's own 8 px at 512 (its model_index.json), as the demo grows them; timed with the
cache as training left it, then again in a copy of the edit with the cache warm), edit (sheet 0;
every NeRF training under `--edit_seconds`; the evaluation as a user gets it, without its
costlier parts), then `signerf eval --edit` with those parts turned on (independent per-view
edits and their correspondences, the before/after video: `COMPARISONS`), timed apart. The same
edit runs again with whole downscaled frames instead of selection crops (`SheetConfig.crops =
False`): the crops comparison. Writes into --results DIR (default outputs/experiments/)
real_scene_edit.json (each command's wall seconds, the edit's stage seconds, the evaluation's
metrics, the crops comparison, the machine and its load) and real_scene_edit.png (the
placement, the preview, before/after held-out renders with crops and with whole frames).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

from signerf_jax import files, ownership
from signerf_jax.editing import figures, generation
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from signerf_jax.editing.commands import sweeps

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))
DOWNSCALE = 4  # 200 x 200 px views.
VIEW = "0002.png"
PIXEL = (155.0, 150.0)  # On the table, in front of the toy's right foot (200 px view).
PROMPT = "a red teddy bear"
# The evaluation's costlier parts, which an edit leaves out unless asked (as the demo asks).
COMPARISONS = ("EvaluationConfig.independent_views = 12", "EvaluationConfig.video_frames = 48")


def signerf(cache: Path, *argv) -> tuple[float, str]:
  """Runs `signerf ARGV` in a new process with compilation cache `cache`: (wall seconds, its
  stdout). Fails on an error."""
  start = time.perf_counter()
  command = [sys.executable, "-m", "signerf_jax.cli", *map(str, argv)]
  done = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=False,
                        env={**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache)})
  if done.returncode != 0:
    raise SystemExit(f"{' '.join(command)} failed with exit code {done.returncode}")
  return time.perf_counter() - start, done.stdout


def edit_quality(metrics: dict) -> dict:
  """The headline numbers of an edit's metrics.json (`sweeps.edit_quality`), the image set's
  prompt colour and proxy shape, and its stages' seconds."""
  return {**sweeps.edit_quality(metrics),
          "prompt_color_share_images": metrics["prompt_color_adherence"]["image_set"]["share"],
          "shape_iou_images": metrics["shape_iou"]["image_set"],
          "stage_seconds": metrics["stage_seconds"]}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="outputs/real_scene_edit")
  parser.add_argument("--train_seconds", type=float, default=300.0)
  parser.add_argument("--edit_seconds", type=float, default=120.0)
  results_dir.add_argument(parser)
  args = parser.parse_args()
  load_at_start = os.getloadavg()
  out = Path(args.out)
  run, edit, warm, full_frames = (out / "run", out / "edit", out / "edit_warm_preview",
                                  out / "edit_full_frames")
  cache = out / "compilation_cache"
  for directory in (edit, warm, full_frames):
    ownership.clear(directory, ownership.EDIT)
  shutil.rmtree(cache, ignore_errors=True)  # The experiment's own compilation cache.
  seconds = {}
  seconds["train"], _ = signerf(cache, "train", "--data", SHARED_DATA / "stitch", "--run", run,
                                "--downscale", DOWNSCALE, "--max_seconds", args.train_seconds)
  seconds["info"], info = signerf(cache, "info", "--run", run)
  seconds["place"], placed = signerf(
      cache, "place", "--run", run, "--edit", edit, "--view", VIEW, "--pixel", *PIXEL,
      "--proxy", SHARED_DATA / "meshes" / "teddy.obj", "--size_fraction", 0.3)
  shutil.copytree(edit, warm)
  preview = ("--prompt", PROMPT, "--quiet")
  seconds["preview"], _ = signerf(cache, "preview", "--edit", edit, *preview)
  seconds["preview_warm_cache"], _ = signerf(cache, "preview", "--edit", warm, *preview)
  shutil.copytree(edit, full_frames)
  edit_flags = ("--sheet", "0", "--max_seconds", args.edit_seconds, "--quiet")
  seconds["edit"], _ = signerf(cache, "edit", "--edit", edit, *edit_flags)
  edit_metrics = files.read_json(edit / "evaluation" / "metrics.json")
  comparison_flags = [flag for binding in COMPARISONS for flag in ("--gin_param", binding)]
  seconds["eval_with_comparisons"], _ = signerf(cache, "eval", "--edit", edit, *comparison_flags)
  # Whole frames: for the quality comparison, with the comparisons in the edit itself.
  seconds["edit_full_frames"], _ = signerf(cache, "edit", "--edit", full_frames, *edit_flags,
                                           "--gin_param", "SheetConfig.crops = False",
                                           *comparison_flags)
  comparisons = files.read_json(edit / "evaluation" / "metrics.json")
  result = {
      "what": "a real 360-degree capture edited end to end with the shipped model: "
              "train, info, place, preview, edit (commands' wall seconds, stage seconds, "
              "the evaluation)",
      "scene": "stitch", "downscale": DOWNSCALE, "view": VIEW, "pixel": PIXEL,
      "prompt": PROMPT, "mask_dilation": generation.recommended_mask_dilation(DEFAULT_MODEL_DIR),
      "train_seconds_budget": args.train_seconds, "edit_seconds_budget": args.edit_seconds,
      "command_seconds": seconds,
      "nerf": {key: files.read_json(run / "eval.json")[key] for key in (
          "seconds_trained", "held_out", "generalisation_gap_db")},
      "placement": json.loads(placed), "scene_info": {
          key: value for key, value in json.loads(info).items() if key != "views"},
      "metrics": edit_metrics,
      "comparisons": {key: comparisons[key] for key in ("independent_edits", "consistency")},
      # The crops' correspondences from the evaluation with comparisons (same edit).
      "crops_comparison": {"crops": edit_quality({**edit_metrics,
                                                  "consistency": comparisons["consistency"]}),
                           "full_frames": edit_quality(files.read_json(
                               full_frames / "evaluation" / "metrics.json"))},
      "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                  "load_average_at_start": load_at_start,
                  "load_average_at_end": os.getloadavg(), **machine.code_version()},
  }
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / "real_scene_edit.json", result)
  panels = [("placement (signerf place)", edit / "placement.png"),
            ("preview: candidate sheets 0-3", edit / "preview" / "preview.png"),
            ("held-out views before / after (selection crops, the default)",
             edit / "evaluation" / "before_after.png"),
            ("held-out views before / after (whole downscaled frames)",
             full_frames / "evaluation" / "before_after.png")]
  images = [figures.image_grid([[files.read_image(path)]], [[label]]) for label, path in panels]
  files.write_image(args.results / "real_scene_edit.png", plotting.stacked(images))
  print(json.dumps({"command_seconds": seconds, "background_psnr":
                    edit_metrics["background"]["psnr_paper"]}))


if __name__ == "__main__":
  main()
