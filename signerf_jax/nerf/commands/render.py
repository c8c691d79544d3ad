"""`signerf render`: render a trained run's views (colour PNG, depth EXR) and a camera-path video."""

from __future__ import annotations

import argparse
from pathlib import Path

from signerf_jax import cli, ownership
from signerf_jax.nerf import camera_paths, evaluate, render
from signerf_jax.nerf.commands import load_recorded_dataset
from signerf_jax.nerf.commands.evaluate import add_supersampling
from signerf_jax.validation import PositiveInt, argument_type


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--run", required=True, help="run directory written by `signerf train`")
  cli.add_output_argument(parser, "--out", default=None,
                          help="output directory: new, empty, or renders signerf wrote (default: "
                          "RUN/renders); writes SPLIT/<view>.png, .depth.exr, .depth.png, "
                          ".accumulation.png and video.mp4 there")
  parser.add_argument("--split", default="eval", choices=("train", "eval", "all"),
                      help="which dataset views to render")
  parser.add_argument("--video", action="store_true", help="also render a camera-path video")
  parser.add_argument("--frames", type=argument_type(PositiveInt), default=60,
                      help="video length in frames")
  parser.add_argument("--chunk_size", type=argument_type(PositiveInt),
                      default=render.DEFAULT_CHUNK_SIZE, help="rays rendered at once")
  add_supersampling(parser)


def run(args: argparse.Namespace) -> int:
  render.check_chunk_size(args.chunk_size, "--chunk_size")  # Before the run is loaded.
  trained = evaluate.load_run(args.run)
  dataset = load_recorded_dataset(trained.description, args.split)
  if args.out:
    out = Path(args.out)
    claim = ownership.claimed(out, ownership.RENDERS,
                              inputs=(("run", args.run), ("data", dataset.root)))
  else:  # Into the run, which must be one signerf made.
    out = Path(args.run) / "renders"
    claim = ownership.claimed(args.run, ownership.RUN, flag="run")
  with claim:
    outputs = render.render_cameras(trained.model, trained.variables, dataset.cameras,
                                    args.chunk_size, supersampling=args.supersampling)
    render.write_renders(out / args.split, dataset.image_names, outputs)
    message = f"{dataset.num_images} {args.split} views in {out / args.split}"
    if args.video:
      path_cameras = camera_paths.orbit_cameras(trained.model, dataset.cameras, args.frames)
      frames = render.render_cameras(trained.model, trained.variables, path_cameras,
                                     args.chunk_size, supersampling=args.supersampling)["rgb"]
      message += f", video {render.write_video(out / 'video.mp4', frames)}"
  print(f"signerf render: {message}")
  return 0
