"""The fused CPU attention kernel at several revisions of its source, side by side.

  python experiments/bench_kernel_revisions.py --revisions c929b9f worktree [--repeats 21]
      [--shapes 2x4096x8x40 2x1024x8x80 2x256x8x160] [--name bench_kernel_revisions]

Each revision's signerf_jax/diffusion/cpu_attention.cc (`git show REV:...`; "worktree" is the file
as it is now) is built through `cpu_attention.build` (the same compiler, flags and cache) and
registered as its own FFI target, so all run in one process on the same inputs: one call of each
per round, in turn, after a warm-up (bench_attention.alternate), for `repeats` rounds. Shapes are
[batch, tokens, heads, head size] self-attentions (the defaults: SD 1.5's at a 64x64 latent,
levels 0-2). Reported per shape and revision: the seconds of every round, their median, GFLOP/s
(4 B T^2 H D), the median of the paired speed-ups over the first revision with their range, and the
largest output difference from the first revision.
Writes <name>.json with the machine and its load into --results DIR (default
outputs/experiments/).
"""

from __future__ import annotations

import argparse
import os
import subprocess
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import machine
import results_dir
from bench_attention import alternate, compiled
from signerf_jax import files
from signerf_jax.diffusion import cpu_attention

REPOSITORY = Path(__file__).resolve().parent.parent
KERNEL_PATH = "signerf_jax/diffusion/cpu_attention.cc"  # In this checkout, as git names it.


def git(*arguments: str) -> str:
  return subprocess.run(["git", *arguments], cwd=REPOSITORY, capture_output=True, text=True,
                        check=True).stdout


def revision_source(revision: str) -> str:
  """The kernel's source at a git `revision`, or as it is now for "worktree"."""
  if revision == "worktree":
    return (REPOSITORY / KERNEL_PATH).read_text()
  return git("show", f"{revision}:{KERNEL_PATH}")


def kernel_call(target_name: str):
  """One call of the FFI target (cpu_attention's own call, `_ffi_attention`, fixes the name)."""
  return lambda query, key, value: jax.ffi.ffi_call(
      target_name, jax.ShapeDtypeStruct(query.shape, jnp.float32))(query, key, value)


def measure(targets: dict[str, str], shape: tuple[int, ...], repeats: int) -> dict:
  """Every revision's kernel (revision -> FFI target) on one random [B, T, H, D] self-attention."""
  random = np.random.default_rng(0)
  query, key, value = (jnp.asarray(random.standard_normal(shape), jnp.float32) for _ in range(3))
  query = query * shape[-1]**-0.5
  programs = {revision: compiled(kernel_call(target), (query, key, value))
              for revision, target in targets.items()}
  first = next(iter(programs))
  expected = programs[first](query, key, value)
  timed = alternate({revision: lambda _, program=program: program(query, key, value)
                     for revision, program in programs.items()}, first, repeats)
  batch, tokens, heads, head_dim = shape
  gflop = 4 * batch * tokens**2 * heads * head_dim / 1e9
  for revision, program in programs.items():
    timed[revision]["gflops_per_second"] = round(gflop / timed[revision]["median_seconds"], 1)
    timed[revision]["max_abs_difference"] = float(
        jnp.abs(program(query, key, value) - expected).max())
  return {"shape": list(shape), "gflop": gflop, "revisions": timed}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--revisions", nargs="+", required=True,
                      help="git revisions of the kernel, or worktree; the first is the baseline")
  parser.add_argument("--shapes", nargs="+",
                      default=["2x4096x8x40", "2x1024x8x80", "2x256x8x160"])
  parser.add_argument("--repeats", type=int, default=21, help="timed rounds")
  parser.add_argument("--name", default="bench_kernel_revisions", help="results/<name>.json")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  if reason := cpu_attention.unmet_requirement():
    raise SystemExit(f"the fused kernel cannot run here: {reason}")
  result = {"what": __doc__.split("\n\n")[1].replace("\n", " "),
            "machine": machine.record(), "repeats": args.repeats, "revisions": {}, "shapes": {}}
  targets = {}
  for index, revision in enumerate(args.revisions):
    source = revision_source(revision)
    targets[revision] = f"{cpu_attention.TARGET_NAME}_revision_{index}"
    cpu_attention.register(cpu_attention.build(source), targets[revision])
    result["revisions"][revision] = (
        "the working tree" if revision == "worktree" else git("rev-parse", revision).strip())
  for text in args.shapes:
    shape = tuple(int(size) for size in text.split("x"))
    result["shapes"][text] = measure(targets, shape, args.repeats)
    print(text, {revision: (found["median_seconds"], found["gflops_per_second"],
                            found["speedup_over_baseline"])
                 for revision, found in result["shapes"][text]["revisions"].items()}, flush=True)
  result["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", result)
  print(f"bench_kernel_revisions: results in {args.results / args.name}.json")


if __name__ == "__main__":
  main()
