"""`signerf process`: a folder of photos or a video, without camera poses, into a nerfstudio
dataset the rest of the project reads, with the poses COLMAP recovers (`structure_from_motion`).

DATA holds: images/ (the photos, upright, or the video's sharpest frames), images_2/, images_4/,
images_8/ (downscaled copies), colmap/database.db (features and matches, which a rerun reuses),
colmap/sparse/0/ (the kept model, COLMAP's binary files), transforms.json (the registered
images) and process.json (the summary, also printed as one JSON line).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Iterator, get_args

from signerf_jax import cli, files, ownership
from signerf_jax.errors import InputError
from signerf_jax.validation import PositiveInt, argument_type

COLMAP_FOLDER, DATABASE_NAME, STATE_NAME, SUMMARY_NAME = (
    "colmap", "database.db", "state.json", "process.json")
SPARSE_FOLDER = "colmap/sparse/0"
# Fewer registered images than this, or than half of them, cannot be trained on usefully.
MIN_REGISTERED_IMAGES = 5
DEFAULT_MAX_FRAMES = 300
ADVICE = ("the images must overlap more for COLMAP to tie them together: every part of the "
          "scene in three or more photos taken a step apart (60-80% overlap), sharp (no motion "
          "blur: move slowly, or more --max_frames from a video), lit evenly and with texture; "
          "or find more features: --max_image_size 1600 --max_features 8192")


def add_arguments(parser: argparse.ArgumentParser) -> None:
  from signerf_jax.data import structure_from_motion as sfm

  defaults = sfm.Settings()
  source = parser.add_mutually_exclusive_group(required=True)
  source.add_argument("--images", type=Path, help="folder of photos (jpg, png, tif, bmp, webp)")
  source.add_argument("--video", type=Path, help="video file (whatever OpenCV decodes: mp4, mov, "
                      "avi, ...)")
  cli.add_output_argument(parser, "--out", required=True,
                          help="dataset directory to write: new, empty, or one `signerf "
                          "process` wrote (a rerun resumes)")
  parser.add_argument("--max_frames", type=argument_type(PositiveInt),
                      default=DEFAULT_MAX_FRAMES, help="frames kept from a video")
  parser.add_argument("--camera_model", choices=get_args(sfm.CameraModel),
                      default=defaults.camera_model,
                      help="lens distortion: OPENCV (k1 k2 p1 p2) or SIMPLE_RADIAL (k1)")
  parser.add_argument("--camera_per_image", action="store_true",
                      help="give each image its own camera (photos from several devices or "
                      "zooms); by default all share one")
  parser.add_argument("--matching", choices=get_args(sfm.Matching), default=defaults.matching,
                      help=f"image pairs matched: every pair, or neighbours in name order plus "
                      f"look-alikes; auto is exhaustive up to {defaults.exhaustive_limit} images")
  parser.add_argument("--max_image_size", type=argument_type(PositiveInt),
                      default=defaults.max_image_size,
                      help="features are found in images at most this many pixels wide")
  parser.add_argument("--max_features", type=argument_type(PositiveInt),
                      default=defaults.max_features, help="SIFT features per image")
  parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
  from signerf_jax.data import structure_from_motion as sfm

  settings = sfm.Settings(camera_model=args.camera_model, shared_camera=not args.camera_per_image,
                          matching=args.matching, max_image_size=args.max_image_size,
                          max_features=args.max_features)
  source_flag = "images" if args.images is not None else "video"
  source = args.images if args.images is not None else args.video
  with ownership.claimed(args.out, ownership.DATASET, inputs=[(source_flag, source)], flag="out"):
    summary = process(Path(source), source_flag, Path(args.out), settings, args.max_frames,
                      progress=not args.quiet)
  print(json.dumps(summary))
  return 0


@contextlib.contextmanager
def _step(name: str, seconds: dict[str, float], total: int | None, unit: str,
          progress: bool) -> Iterator[Any]:
  """A progress bar on stderr for one step (unless not `progress`), and its duration into
  `seconds[name]`."""
  import tqdm

  start = time.perf_counter()
  with tqdm.tqdm(total=total, desc=name, unit=unit, dynamic_ncols=True, file=sys.stderr,
                 disable=not progress) as bar:
    yield bar.update
  seconds[name] = round(time.perf_counter() - start, 2)


def process(source: Path, kind: str, dataset: Path, settings, max_frames: int,
            progress: bool = True) -> dict[str, Any]:
  """Runs every step (see the module docstring) in the claimed `dataset`, with progress bars on
  stderr if `progress`; returns the summary."""
  from signerf_jax.data import capture_import, reconstruction_export
  from signerf_jax.data import structure_from_motion as sfm

  sfm.quiet_logging()
  seconds: dict[str, float] = {}
  _start_over_if_changed(dataset, _source_fingerprint(source, kind, max_frames), settings)
  names = _import_images(source, kind, dataset, max_frames, seconds, progress)
  with _step("downscaled copies", seconds, len(names), "image", progress) as advance:
    capture_import.write_downscaled(dataset, names, advance)
  database = dataset / COLMAP_FOLDER / DATABASE_NAME
  ownership.record_written(database)
  image_folder = dataset / capture_import.IMAGE_FOLDER
  with _step("features", seconds, len(names), "image", progress) as advance:
    extracted = sfm.extract_features(database, image_folder, names, settings, advance)
  pairs = sfm.pairs_to_match(database, names, settings)
  with _step("matching", seconds, len(pairs), "pair", progress) as advance:
    matched = sfm.match(database, pairs, advance)
  with _step("mapping", seconds, len(names), "image", progress) as advance:
    models = sfm.reconstruct(database, image_folder, len(names), settings, advance)
  members = [sorted(model.images[i].name for i in model.reg_image_ids()) for model in models]
  summary = {
      "images": len(names), "registered": len(members[0]) if members else 0,
      "unregistered": sorted(set(names).difference(*members)),
      "other_models": members[1:],
      "matching": settings.matching_for(len(names)), "pairs": len(pairs),
      "features_extracted": extracted, "pairs_matched": matched, "seconds": seconds,
  }
  _check_enough(summary, dataset)
  model = models[0]
  errors = reconstruction_export.reprojection_errors(model)
  summary.update(points=len(errors), mean_reprojection_error_px=round(float(errors.mean()), 4),
                 camera=reconstruction_export.camera_entry(model.cameras[
                     model.images[model.reg_image_ids()[0]].camera_id]))
  start = time.perf_counter()
  reconstruction_export.write_sparse_model(model, dataset / SPARSE_FOLDER)
  files.write_json(dataset / "transforms.json", reconstruction_export.transforms(
      model, capture_import.IMAGE_FOLDER, {"command": "signerf process", "source": str(source)}))
  seconds["writing"] = round(time.perf_counter() - start, 2)
  files.write_json(dataset / SUMMARY_NAME, summary)
  _report(summary)
  return summary


def _import_images(source: Path, kind: str, dataset: Path, max_frames: int,
                   seconds: dict[str, float], progress: bool) -> list[str]:
  """The capture's images written into `dataset/images/` (see `capture_import`)."""
  from signerf_jax.data import capture_import

  if kind == "images":
    count = len(capture_import.photo_names(source))
    with _step("photos", seconds, count, "image", progress) as advance:
      return capture_import.import_photos(source, dataset, advance)
  # One bar over both readings of the video: every frame's sharpness, then the chosen frames.
  with _step("video frames", seconds, None, "frame", progress) as advance:
    return capture_import.import_video(source, dataset, max_frames, advance, advance)


def _source_fingerprint(source: Path, kind: str, max_frames: int) -> dict[str, Any]:
  """What the imported images depend on: the source's files (name, size, modification time)
  and, for a video, the number of frames kept."""
  if kind == "images" and source.is_dir():
    listed = sorted(path for path in source.iterdir() if path.is_file())
  else:
    listed = [source] if source.is_file() else []
  found = [[path.name, path.stat().st_size, path.stat().st_mtime_ns] for path in listed]
  return {"kind": kind, "files": found, "max_frames": max_frames if kind == "video" else None}


def _start_over_if_changed(dataset: Path, fingerprint: dict[str, Any], settings) -> None:
  """Keeps an earlier run's images and database only if they came from the same source and
  settings: otherwise deletes what it wrote (the images, or only the database)."""
  state_path = dataset / COLMAP_FOLDER / STATE_NAME
  state = files.read_json(state_path) if state_path.is_file() else None
  if state is None or state.get("source") != fingerprint:
    ownership.remove_written(dataset)
  elif state.get("features") != settings.feature_fingerprint():
    ownership.remove_written(dataset / COLMAP_FOLDER)
  files.write_json(state_path, {"source": fingerprint,
                                "features": settings.feature_fingerprint()})


def _check_enough(summary: dict[str, Any], dataset: Path) -> None:
  """Raises when too few images registered to train on (fewer than half or than
  MIN_REGISTERED_IMAGES), naming how many and what to try."""
  needed = max(MIN_REGISTERED_IMAGES, math.ceil(summary["images"] / 2))
  if summary["registered"] < needed:
    files.write_json(dataset / SUMMARY_NAME, summary)
    raise InputError(f"only {summary['registered']} of {summary['images']} images registered "
                     f"(at least {needed} are needed to train; process.json lists the others): "
                     f"{ADVICE}", dataset, "out")


def _report(summary: dict[str, Any]) -> None:
  """Says on stderr which images did not register and which formed separate models."""
  if summary["unregistered"]:
    names = summary["unregistered"]
    print(f"signerf process: {len(names)} of {summary['images']} images did not register and are "
          f"left out: {', '.join(names)}", file=sys.stderr)
  for index, names in enumerate(summary["other_models"], 2):
    print(f"signerf process: COLMAP found a separate model {index} of {len(names)} images, not "
          f"tied to the kept one (they are left out): {', '.join(names)}", file=sys.stderr)
