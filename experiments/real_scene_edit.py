"""A real-scene edit end to end, as a user runs it: the 360-degree phone capture
../shared/data/stitch (a toy on a table, the room behind), a teddy-bear mesh from
../shared/data/meshes placed on the table with `signerf place`, the preview, the edit and its
evaluation with the shipped model.

  python experiments/real_scene_edit.py [--out outputs/real_scene_edit] [--train_seconds 300]
      [--edit_seconds 120]

Every step is the `signerf` command a user types (run in this process; the NeRF is reused when
OUT/run exists, and then its command only resumes and evaluates: the NeRF's own training seconds
are recorded apart): train (time budget `--train_seconds`), info, place (view 0, a pixel on the
table in front of the toy), preview (four candidate sheets), edit (sheet 0; every NeRF training
under `--edit_seconds`). Writes experiments/results/real_scene_edit.json (each command's wall
seconds, the edit's stage seconds, the evaluation's metrics, the machine and its load) and
real_scene_edit.png (the placement, the preview, the chosen sheet, before/after held-out
renders).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from signerf_jax import cli, files
from signerf_jax.editing import figures

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))
DOWNSCALE = 4  # 200 x 200 px views.
VIEW = "0002.png"
PIXEL = (155.0, 150.0)  # On the table, in front of the toy's right foot (200 px view).
PROMPT = "a red teddy bear"


def signerf(*argv: str) -> tuple[float, str]:
  """Runs `signerf ARGV` in this process: (wall seconds, its stdout). Fails on an error."""
  start = time.perf_counter()
  stdout = io.StringIO()
  with contextlib.redirect_stdout(stdout):
    code = cli.main([str(value) for value in argv])
  if code != 0:
    raise SystemExit(f"signerf {' '.join(map(str, argv))} failed with exit code {code}")
  return time.perf_counter() - start, stdout.getvalue()


def stacked(images: list[np.ndarray]) -> np.ndarray:
  """Images [H_i, W_i, 3] one above the other, left-aligned on white."""
  width = max(image.shape[1] for image in images)
  return np.concatenate([np.pad(image, ((0, 8), (0, width - image.shape[1]), (0, 0)),
                                constant_values=1.0) for image in images])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="outputs/real_scene_edit")
  parser.add_argument("--train_seconds", type=float, default=300.0)
  parser.add_argument("--edit_seconds", type=float, default=120.0)
  args = parser.parse_args()
  load_at_start = os.getloadavg()
  out = Path(args.out)
  run, edit = out / "run", out / "edit"
  seconds = {}
  seconds["train"], _ = signerf("train", "--data", SHARED_DATA / "stitch", "--out", run,
                                "--downscale", DOWNSCALE, "--max_seconds", args.train_seconds)
  seconds["info"], info = signerf("info", "--run", run)
  seconds["place"], placed = signerf(
      "place", "--run", run, "--out", edit, "--view", VIEW, "--pixel", *PIXEL,
      "--proxy", SHARED_DATA / "meshes" / "teddy.obj", "--size_fraction", 0.3)
  seconds["preview"], _ = signerf("preview", "--out", edit, "--prompt", PROMPT, "--quiet")
  seconds["edit"], _ = signerf("edit", "--out", edit, "--sheet", "0", "--max_seconds",
                               args.edit_seconds, "--quiet")
  metrics = files.read_json(edit / "evaluation" / "metrics.json")
  result = {
      "what": "a real 360-degree capture edited end to end with the shipped model: "
              "train, info, place, preview, edit (commands' wall seconds, stage seconds, "
              "the evaluation)",
      "scene": "stitch", "downscale": DOWNSCALE, "view": VIEW, "pixel": PIXEL,
      "prompt": PROMPT, "train_seconds_budget": args.train_seconds,
      "edit_seconds_budget": args.edit_seconds, "command_seconds": seconds,
      "nerf": {key: files.read_json(run / "eval.json")[key] for key in (
          "seconds_trained", "held_out", "generalisation_gap_db")},
      "placement": json.loads(placed), "scene_info": {
          key: value for key, value in json.loads(info).items() if key != "views"},
      "metrics": metrics,
      "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                  "load_average_at_start": load_at_start,
                  "load_average_at_end": os.getloadavg()},
  }
  RESULTS.mkdir(parents=True, exist_ok=True)
  files.write_json(RESULTS / "real_scene_edit.json", result)
  panels = [("placement (signerf place)", edit / "placement.png"),
            ("preview: candidate sheets 0-3", edit / "preview" / "preview.png"),
            ("held-out views before / after", edit / "evaluation" / "before_after.png")]
  images = [figures.image_grid([[files.read_image(path)]], [[label]]) for label, path in panels]
  files.write_image(RESULTS / "real_scene_edit.png", stacked(images))
  print(json.dumps({"command_seconds": seconds, "background_psnr":
                    metrics["background"]["psnr_paper"]}))


if __name__ == "__main__":
  main()
