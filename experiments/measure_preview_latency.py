"""How long a user waits for the first preview of a placed edit, on a machine's first run.

    python experiments/measure_preview_latency.py [--edit outputs/real_scene_edit/edit]
        [--sources this=. before=/path/to/an/older/checkout] [--repeats 2] [--out DIR]
        [--initial_cache DIR] [--name preview_latency]

Issue 18 asks that, with a trained NeRF, the first sheet preview appears within 30 s on this
CPU. This runs `signerf preview` as a user does, each time in a new process with an empty JAX
compilation cache (nothing compiled before, the worst case) or a copy of `--initial_cache`
(what a user has after training: e.g. `JAX_COMPILATION_CACHE_DIR=DIR signerf train --data
../shared/data/stitch --downscale 4 --max_seconds 20 --out RUN` leaves the programs the
300-s run of real_scene_edit.py compiles), on
a copy of a placed edit (experiments/real_scene_edit.py's teddy bear on the real capture
stitch, by default), and
records when preview.png first appears (the first candidate sheet), when the command ends
(every candidate) and each stage's seconds. Given several source trees (`--sources
LABEL=DIR`, e.g. a git worktree of an older commit), their runs alternate, so that they are
compared side by side on the same machine state.
Writes experiments/results/NAME.json.
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

from signerf_jax import files

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position

RESULTS = Path(__file__).resolve().parent / "results"
PROMPT = "a teddy bear"


def timed_preview(source: Path, edit: Path, cache: Path, initial_cache: Path | None) -> dict:
  """Runs the preview of `edit` with the code in `source` and the compilation cache `cache`,
  empty or a copy of `initial_cache`: seconds to the first preview.png and to the end, and the
  stages' seconds."""
  shutil.rmtree(cache, ignore_errors=True)
  if initial_cache is not None:
    shutil.copytree(initial_cache, cache)
  preview_png = edit / "preview" / "preview.png"
  command = [sys.executable, "-m", "signerf_jax.cli", "preview", "--out", str(edit.resolve()),
             "--prompt", PROMPT, "--quiet"]
  start = time.perf_counter()
  # In `source` (python -m puts the working directory first on the path) with its code.
  process = subprocess.Popen(command, cwd=source, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, env={
                                 **os.environ, "PYTHONPATH": str(source),
                                 "JAX_COMPILATION_CACHE_DIR": str(cache.resolve())})
  first = None
  while process.poll() is None:
    if first is None and preview_png.is_file():
      first = time.perf_counter() - start
    time.sleep(0.05)
  total = time.perf_counter() - start
  if process.returncode != 0:
    raise SystemExit(f"{' '.join(command)} (PYTHONPATH={source}) failed with exit code "
                     f"{process.returncode}")
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
  parser.add_argument("--initial_cache", default=None,
                      help="a compilation cache each run starts from (default: an empty one)")
  parser.add_argument("--name", default="preview_latency", help="the results file's name")
  args = parser.parse_args()
  placed = Path(args.edit) / "config.gin"
  if not placed.is_file():
    raise SystemExit(f"{placed}: no placed edit here (run experiments/real_scene_edit.py)")
  sources = dict(text.split("=", 1) for text in args.sources)
  record = machine.record()
  runs: dict[str, list[dict]] = {label: [] for label in sources}
  for repeat in range(args.repeats):
    for label, source in sources.items():
      edit = Path(args.out) / label
      shutil.rmtree(edit, ignore_errors=True)
      edit.mkdir(parents=True)
      shutil.copy(placed, edit / "config.gin")
      runs[label].append(timed_preview(Path(source).resolve(), edit,
                                       Path(args.out) / "compilation_cache",
                                       args.initial_cache and Path(args.initial_cache)))
      print(f"{label} run {repeat + 1}: {runs[label][-1]}", flush=True)
  summary = {label: {key: statistics.median(run[key] for run in measured)
                     for key in ("first_candidate_seconds", "all_candidates_seconds")}
             for label, measured in runs.items()}
  RESULTS.mkdir(parents=True, exist_ok=True)
  files.write_json(RESULTS / f"{args.name}.json", {
      "what": "`signerf preview` on a placed edit of a trained NeRF, each run a new process with "
              "a compilation cache that starts empty or as `initial_cache`: seconds until "
              "preview.png first appears (the first candidate sheet) and until the command ends "
              "(every candidate); medians over the repeats, the runs of the source trees "
              "alternating",
      "initial_cache": args.initial_cache,
      "edit": str(Path(args.edit).resolve()), "prompt": PROMPT,
      "sources": {label: str(Path(source).resolve()) for label, source in sources.items()},
      "median": summary, "runs": runs,
      "machine": {**record, "load_average_at_end": os.getloadavg()}})


if __name__ == "__main__":
  main()
