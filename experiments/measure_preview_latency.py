"""How long a user waits for the first preview of a placed edit, on a machine's first run.

    python experiments/measure_preview_latency.py [--edit outputs/real_scene_edit/edit]
        [--sources this=. before=/path/to/an/older/checkout] [--repeats 2] [--out DIR]
        [--after_training] [--name preview_latency]

Issue 18 asks that, with a trained NeRF, the first sheet preview appears within 30 s on this
CPU. This runs `signerf preview` as a user does, each time in a new process, on a copy of a
placed edit (experiments/real_scene_edit.py's teddy bear on the real capture stitch, by
default), with a JAX compilation cache that starts empty (nothing compiled before, the worst
case) or, with `--after_training`, as a user's cache is after `signerf train` and `signerf
place` of the scene (each source tree's own: its `signerf train --max_seconds 20` and `signerf
place` run once first, compiling what the 300-s training and the placement compile). The cache
is always at the same path: JAX's cache keys name the cache directory (its GPU autotuning cache
option), so a cache copied elsewhere would hit nothing. It records when preview.png first
appears (the first candidate sheet), when the command ends (every candidate) and each stage's
seconds. Given several source trees (`--sources LABEL=DIR`, e.g. a git worktree of an older
commit), their runs alternate, so that they are compared side by side on the same machine
state.
Writes NAME.json into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from signerf_jax import files, ownership

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import real_scene_edit  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

PROMPT = "a teddy bear"


def launch(source: Path, cache: Path, *argv) -> subprocess.Popen:
  """Starts `signerf ARGV` quietly with the code in `source` and the compilation cache `cache`."""
  command = [sys.executable, "-m", "signerf_jax.cli", *map(str, argv)]
  # In `source` (python -m puts the working directory first on the path) with its code. The
  # threshold is the one `signerf` sets for a user's cache: older trees kept JAX's 1 s when the
  # directory came from JAX_COMPILATION_CACHE_DIR.
  return subprocess.Popen(command, cwd=source, stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL, env={
                              **os.environ, "PYTHONPATH": str(source),
                              "JAX_COMPILATION_CACHE_DIR": str(cache.resolve()),
                              "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.1"})


def check(process: subprocess.Popen, source: Path) -> None:
  """Fails unless `process` (of the code in `source`) succeeds."""
  if process.wait() != 0:
    raise SystemExit(f"{' '.join(process.args)} (PYTHONPATH={source}) failed with exit code "
                     f"{process.returncode}")


def signerf(source: Path, cache: Path, *argv) -> None:
  """Runs `signerf ARGV` as `launch` starts it; fails on an error."""
  check(launch(source, cache, *argv), source)


def cache_after_training(source: Path, work: Path, cache: Path) -> Path:
  """A copy of the compilation cache `cache` as experiments/real_scene_edit.py's `signerf train`
  and `signerf place` leave it, run with the code in `source` (a 20-s training: the same
  programs as a longer one)."""
  shutil.rmtree(cache, ignore_errors=True)
  ownership.clear(work / "run", ownership.RUN)
  ownership.clear(work / "edit", ownership.EDIT)
  shutil.rmtree(work / "compilation_cache", ignore_errors=True)  # Made below, from `cache`.
  signerf(source, cache, "train", "--data", real_scene_edit.SHARED_DATA / "stitch", "--downscale",
          real_scene_edit.DOWNSCALE, "--max_seconds", 20, "--out", work / "run")
  signerf(source, cache, "place", "--run", work / "run", "--out", work / "edit", "--view",
          real_scene_edit.VIEW, "--pixel", *real_scene_edit.PIXEL, "--proxy",
          real_scene_edit.SHARED_DATA / "meshes" / "teddy.obj", "--size_fraction", 0.3)
  saved = work / "compilation_cache"
  shutil.move(cache, saved)
  return saved


def timed_preview(source: Path, edit: Path, placed: Path, cache: Path,
                  initial_cache: Path | None) -> dict:
  """Runs the preview of `edit` (placed by the config file `placed`) with the code in `source`
  and the compilation cache `cache`,
  empty or a copy of `initial_cache` (made at the same path): seconds to the first preview.png
  and to the end, and the stages' seconds."""
  shutil.rmtree(cache, ignore_errors=True)
  if initial_cache is not None:
    shutil.copytree(initial_cache, cache)
  preview_png = edit / "preview" / "preview.png"
  start = time.perf_counter()
  # `--out`, not `--edit`: the older checkouts compared know only that spelling (still accepted).
  process = launch(source, cache, "preview", "--out", edit.resolve(), "--gin_file", placed,
                   "--prompt", PROMPT, "--quiet")
  first = None
  while process.poll() is None:
    if first is None and preview_png.is_file():
      first = time.perf_counter() - start
    time.sleep(0.05)
  total = time.perf_counter() - start
  check(process, source)
  stages = files.read_json(edit / "stages.json")
  return {"first_candidate_seconds": round(first or total, 2), "all_candidates_seconds":
          round(total, 2), "stage_seconds": {name: round(record["seconds"], 2)
                                             for name, record in stages.items()}}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--edit", default="outputs/real_scene_edit/edit",
                      help="a placed edit (its config.gin: the trained NeRF and the selection)")
  parser.add_argument("--sources", nargs="+", default=["this=."],
                      help="LABEL=DIR: source trees whose `signerf preview` is timed")
  parser.add_argument("--repeats", type=int, default=2)
  parser.add_argument("--out", default="outputs/preview_latency")
  parser.add_argument("--after_training", action="store_true",
                      help="start each run from the cache training and placement leave "
                           "(default: an empty cache)")
  parser.add_argument("--name", default="preview_latency", help="the results file's name")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  placed = Path(args.edit) / "config.gin"
  if not placed.is_file():
    raise SystemExit(f"{placed}: no placed edit here (run experiments/real_scene_edit.py)")
  sources = dict(text.split("=", 1) for text in args.sources)
  cache = Path(args.out) / "compilation_cache"
  initial_caches = {label: cache_after_training(Path(source).resolve(),
                                                Path(args.out) / f"after_training_{label}", cache)
                    for label, source in sources.items() if args.after_training}
  record = machine.record()
  runs: dict[str, list[dict]] = {label: [] for label in sources}
  for repeat in range(args.repeats):
    for label, source in sources.items():
      edit = Path(args.out) / label
      ownership.clear(edit, ownership.EDIT)
      runs[label].append(timed_preview(Path(source).resolve(), edit, placed, cache,
                                       initial_caches.get(label)))
      print(f"{label} run {repeat + 1}: {runs[label][-1]}", flush=True)
  summary = {label: {key: statistics.median(run[key] for run in measured)
                     for key in ("first_candidate_seconds", "all_candidates_seconds")}
             for label, measured in runs.items()}
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / f"{args.name}.json", {
      "what": "`signerf preview` on a placed edit of a trained NeRF, each run a new process with "
              "a compilation cache that starts empty or (after_training) as `signerf train` and "
              "`signerf place` of the scene leave it: seconds until preview.png first appears "
              "(the first candidate sheet) and until the command ends (every candidate); "
              "medians over the repeats, the runs of the source trees alternating",
      "after_training": args.after_training,
      "edit": str(Path(args.edit).resolve()), "prompt": PROMPT,
      "sources": {label: str(Path(source).resolve()) for label, source in sources.items()},
      "median": summary, "runs": runs,
      "machine": {**record, "load_average_at_end": os.getloadavg()}})


if __name__ == "__main__":
  main()
