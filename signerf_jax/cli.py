"""The `signerf` command: one subcommand per pipeline stage.

Each subcommand lives in the module that owns its stage and exposes `add_arguments(parser)` and
`run(args) -> int`. Only the chosen subcommand's module is imported, so `signerf --help` is fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Sequence

from signerf_jax import allocator, ownership
from signerf_jax.errors import InputError

# name -> (module implementing it, one-line help). Stages add themselves here.
COMMANDS: dict[str, tuple[str, str]] = {
    "synthesize": ("signerf_jax.data.commands",
                   "write a synthetic scene with ground-truth depth and object masks"),
    "train": ("signerf_jax.nerf.commands.train", "train (or resume) a NeRF on a dataset"),
    "render": ("signerf_jax.nerf.commands.render",
               "render a trained NeRF's views (PNG, depth EXR) and a camera-path video"),
    "eval": ("signerf_jax.editing.commands.evaluate",
             "evaluate a trained NeRF (PSNR, SSIM, depth error) or an edit (--edit) as one "
             "JSON line"),
    "edit": ("signerf_jax.editing.commands.edit",
             "edit a NeRF scene with a prompt (SIGNeRF): every stage, resumable"),
    "info": ("signerf_jax.nerf.commands.info",
             "a trained run's scene frame, bounds, views and a default proxy size"),
    "place": ("signerf_jax.editing.commands.place",
              "stand a proxy on the surface under a pixel of a training view"),
    "preview": ("signerf_jax.editing.commands.preview",
                "preview candidate reference sheets (seeds side by side, per-tile re-rolls)"),
    "update": ("signerf_jax.editing.commands.edit",
               "update the image set through the chosen sheet; write the edited dataset"),
    "finetune": ("signerf_jax.editing.commands.edit",
                 "fine-tune (or retrain) the NeRF on the edited dataset"),
    "view": ("signerf_jax.viewer.command",
             "the trained NeRF, its cameras and the edit's selection in a browser: move the "
             "selection, preview sheets, save"),
    "demo": ("signerf_jax.editing.demo",
             "insert a cow into a generated scene with the shipped model, end to end"),
}

# Commands whose process keeps the memory XLA frees (signerf_jax.allocator): a NeRF step or a
# rendered chunk frees and re-faults its buffers on every call (`eval` renders the views it
# measures: 1.49x on stitch). `edit` and `demo` too: their time-budgeted NeRF stages run
# ~1.3-1.45x the steps, which outweighs their sampling stages running slower that way; and
# `view`, whose frames of a real capture come 1.57x sooner while its occasional preview samples
# slower. `preview` and `update` only sample and keep glibc's defaults (README, "Performance").
KEEP_FREED_MEMORY_COMMANDS = ("train", "finetune", "render", "eval", "edit", "demo", "view")

# Commands a rerun resumes (checkpoints and finished stages are kept): an interrupted one says so.
RESUMABLE_COMMANDS = ("train", "edit", "update", "finetune", "demo")


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
  """The `signerf` parser; only the subcommand named first in `argv` adds its options."""
  parser = argparse.ArgumentParser(prog="signerf", description=__doc__.splitlines()[0])
  subparsers = parser.add_subparsers(dest="command", required=True)
  for name, (module_name, help_text) in COMMANDS.items():
    subparser = subparsers.add_parser(name, help=help_text, description=help_text)
    subparser.set_defaults(module_name=module_name)
    if argv and argv[0] == name:
      importlib.import_module(module_name).add_arguments(subparser)
  return parser


def use_compilation_cache() -> None:
  """Keeps compiled programs between commands in JAX's persistent cache, so a preview after
  `signerf train`, or the next preview, does not compile the sampler and the renderer again
  (README, "Editing a scene", has the times). JAX's own settings win: JAX_COMPILATION_CACHE_DIR
  chooses another directory, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS another threshold,
  JAX_ENABLE_COMPILATION_CACHE=false turns the cache off."""
  import jax  # pylint: disable=g-import-not-at-top  (`signerf --help` stays fast without it)
  if jax.config.jax_compilation_cache_dir is None:
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    jax.config.update("jax_compilation_cache_dir", str(cache_home / "signerf_jax" / "xla"))
  if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
    # A preview compiles ~90 programs, most under JAX's default 1 s threshold and ~5 s together.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)


def _raise_terminated(signum: int, frame) -> None:
  """SIGTERM's handler while a command runs: stops it as Ctrl-C does (`training_loop`)."""
  del signum, frame
  from signerf_jax import training_loop  # pylint: disable=g-import-not-at-top  (already loaded)
  raise training_loop.Terminated()


def main(argv: Sequence[str] | None = None) -> int:
  """Runs the subcommand `argv` names; returns its exit code: 2 with a message on bad input;
  130 / 143 with one line after SIGINT / SIGTERM (a training run checkpoints its steps first
  and the line names the step and where it was saved)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  args = build_parser(argv).parse_args(argv)
  if args.command in KEEP_FREED_MEMORY_COMMANDS:
    allocator.keep_freed_memory()  # Before JAX starts its threads.
  # Here, not at the top: `signerf --help` stays fast without tqdm.
  from signerf_jax import training_loop  # pylint: disable=g-import-not-at-top
  # SIGTERM (a scheduler's or `kill`'s stop) ends a command as Ctrl-C does, not unannounced and
  # mid-write. Not `view`'s: it stops its server on Ctrl-C only, and SIGTERM's default exit is
  # as clean for it.
  catch_sigterm = (args.command != "view"
                   and threading.current_thread() is threading.main_thread())
  previous_sigterm = signal.signal(signal.SIGTERM, _raise_terminated) if catch_sigterm else None
  try:
    module = importlib.import_module(args.module_name)
    if getattr(args, "out", None):  # Every command names the directory it writes `--out`.
      ownership.check_output_path(args.out)
    use_compilation_cache()
    return int(module.run(args) or 0)
  except InputError as error:
    print(f"signerf {args.command}: error: {error}", file=sys.stderr)
    return 2
  except training_loop.TrainingInterrupted as interruption:
    print(f"signerf {args.command}: {interruption}", file=sys.stderr)
    return interruption.exit_code
  except (KeyboardInterrupt, training_loop.Terminated) as error:
    # Outside a training loop (loading, compiling, an edit's sampling stages): what is written
    # is written atomically, and the resumable commands pick up from it.
    resume = "; run the same command to resume" if args.command in RESUMABLE_COMMANDS else ""
    print(f"signerf {args.command}: interrupted{resume}", file=sys.stderr)
    return 128 + int(training_loop.signal_of(error))
  finally:
    if catch_sigterm:
      signal.signal(signal.SIGTERM, previous_sigterm)


if __name__ == "__main__":
  sys.exit(main())
