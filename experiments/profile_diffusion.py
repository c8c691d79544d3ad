"""Where the UNet's (and UNet + ControlNet's) forward time goes on this CPU, by kind of work.

  python experiments/profile_diffusion.py [--latent_sizes 32 64] [--repeats 2]
      [--name profile_diffusion]

The models are bench_diffusion's SD1.5-shaped UNet and its ControlNet (random weights, batch 2
as under classifier-free guidance, text states [2, 77, 768]), jitted as there, in three
precisions: "fp32"; "bf16", bf16 compute on fp32 weights (bench_diffusion's bf16 option: every
forward casts the weights); "bf16_weights", bf16 compute on weights stored in bf16 (cast once, as
`load_pipeline(dtype=bfloat16, compute_dtype=bfloat16)` stores them). Each is timed (median of
`repeats` forwards after a warm-up, no profiler), then run `repeats` times under `jax.profiler`;
every XLA operation the CPU executed is attributed to a kind of work by the Flax module and
primitive its HLO metadata names (`op_name`, e.g. ".../resnets_0/conv1/dot_general"):
  convolution: matmuls     3x3 and 1x1 convolutions (conv_in/out, resnets, up/downsamplers);
  convolution: taps        their stacking of kernel taps and shifted inputs, and padding;
  dtype conversion         casts (bf16 compute casts fp32 weights and activations), anywhere;
  attention                scores, softmax and the weighted sum (attn1 / attn2);
  attention projections    to_q, to_k, to_v, to_out;
  feed-forward             the transformer's GEGLU (ff);
  transformer projections  proj_in / proj_out;
  normalisation            group norm and layer norm;
  layout                   transposes and copies, wherever they are;
  time embedding, other    the rest (elementwise ops outside the modules above, ...).
Loops (`while`) are not counted themselves: their bodies' operations are. Seconds are the sum of
the operations' durations per forward (operations on different threads add up, so the sum can
exceed the wall time); shares are of that sum. The 10 costliest operations are listed with their
op_name. Writes experiments/results/<name>.json with the machine and its load.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import os
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.profiler import ProfileData

from signerf_jax import files
from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.unet import UNet2DCondition

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
from bench_diffusion import SD15_UNET  # pylint: disable=wrong-import-position

RESULTS = Path(__file__).resolve().parent / "results"
# One HLO instruction line: its name, opcode and metadata's op_name.
INSTRUCTION = re.compile(r'^\s*(?:ROOT\s+)?%?([^\s=]+) = [^=]*?\s([a-z][a-z\-]*)\(.*?'
                         r'op_name="([^"]*)"')
# Path segments that are tracing structure, not modules.
STRUCTURE = {"while", "body", "cond", "closed_call", "checkpoint", "remat", "pjit", "jvp"}
LOOP_OPCODES = {"while", "call", "conditional"}


def kind_of_work(op_name: str, opcode: str) -> str:
  """The kind of work (module docstring) of one HLO operation."""
  segments = [segment for segment in op_name.split("/")[1:] if segment not in STRUCTURE]
  primitive = segments[-1] if segments else ""
  modules = [segment.split(".")[-1] for segment in segments[:-1]]
  if opcode in ("transpose", "copy") or primitive in ("transpose", "copy"):
    return "layout"
  if primitive == "convert_element_type":
    return "dtype conversion"
  innermost = modules[-1] if modules else ""
  if "norm" in innermost:
    return "normalisation"
  if innermost.startswith("conv") or innermost in ("conv", "controlnet_cond_embedding") or any(
      module.startswith(("upsamplers", "downsamplers")) for module in modules):
    matmul = primitive in ("dot_general", "conv_general_dilated")
    return "convolution: matmuls" if matmul else "convolution: taps"
  if innermost in ("to_q", "to_k", "to_v") or innermost.startswith("to_out"):
    return "attention projections"
  if innermost in ("attn1", "attn2"):
    return "attention"
  if "ff" in modules:
    return "feed-forward"
  if innermost in ("proj_in", "proj_out"):
    return "transformer projections"
  if any(module.startswith(("time_embedding", "time_emb_proj", "add_embedding"))
         for module in modules):
    return "time embedding"
  return "other"


def instructions(hlo_text: str) -> dict[str, tuple[str, str]]:
  """{instruction name: (opcode, op_name)} of an optimised HLO module's text."""
  found = {}
  for line in hlo_text.splitlines():
    match = INSTRUCTION.match(line)
    if match:
      found[match.group(1)] = (match.group(2), match.group(3))
  return found


def operation_seconds(trace_directory: str) -> dict[str, float]:
  """{HLO instruction name: seconds executed, summed over every thread} of a trace."""
  paths = list(Path(trace_directory).rglob("*.xplane.pb"))
  seconds: dict[str, float] = collections.Counter()
  for plane in ProfileData.from_file(str(paths[0])).planes:
    for line in plane.lines:
      for event in line.events:
        stats = dict(event.stats)
        if "hlo_op" in stats:
          seconds[stats["hlo_op"]] += event.duration_ns * 1e-9
  return seconds


def profile(function, arguments, repeats: int) -> dict[str, Any]:
  """The breakdown of one jitted forward (module docstring)."""
  compiled = function.lower(*arguments).compile()
  known = instructions(compiled.as_text())
  jax.block_until_ready(function(*arguments))  # Warm-up.
  timed = []
  for _ in range(repeats):
    started = time.perf_counter()
    jax.block_until_ready(function(*arguments))
    timed.append(time.perf_counter() - started)
  with tempfile.TemporaryDirectory() as trace_directory:
    started = time.perf_counter()
    with jax.profiler.trace(trace_directory):
      for _ in range(repeats):
        jax.block_until_ready(function(*arguments))
    wall = (time.perf_counter() - started) / repeats
    executed = operation_seconds(trace_directory)
  by_kind: dict[str, float] = collections.Counter()
  operations = []
  unmatched = 0.0
  for name, seconds in executed.items():
    seconds /= repeats
    if name not in known:
      unmatched += seconds
      continue
    opcode, op_name = known[name]
    if opcode in LOOP_OPCODES:
      continue
    kind = kind_of_work(op_name, opcode)
    by_kind[kind] += seconds
    operations.append((seconds, name, kind, op_name))
  total = sum(by_kind.values())
  operations.sort(reverse=True)
  # Seconds keep microseconds, the trace's resolution: small operations (and small test models)
  # take well under the 0.1 ms that four decimals would keep.
  return {
      "wall_seconds_per_forward": round(float(np.median(timed)), 6),
      "wall_seconds_per_forward_profiled": round(wall, 6),
      "operation_seconds_per_forward": round(total, 6),
      "seconds": {kind: round(value, 6) for kind, value in by_kind.most_common()},
      "share": {kind: round(value / total, 4) for kind, value in by_kind.most_common()},
      "unmatched_seconds": round(unmatched, 6),
      "costliest_operations": [
          {"seconds": round(seconds, 6), "name": name, "kind": kind, "op_name": op_name}
          for seconds, name, kind, op_name in operations[:10]]}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--latent_sizes", type=int, nargs="+", default=[32, 64])
  parser.add_argument("--repeats", type=int, default=3,
                      help="timed and profiled forwards per model and precision")
  parser.add_argument("--name", default="profile_diffusion", help="results/<name>.json")
  args = parser.parse_args()
  result: dict[str, Any] = {
      "machine": machine.record(),
      "repeats": args.repeats, "models": {}}
  unet = UNet2DCondition(model_configs.UNetConfig.from_dict(SD15_UNET))
  controlnet = ControlNet(model_configs.ControlNetConfig.from_dict(
      {**{name: value for name, value in SD15_UNET.items() if name != "sample_size"},
       "conditioning_channels": 3}))
  unet_params, controlnet_params = weights.random_params(unet), weights.random_params(controlnet)
  rng = np.random.default_rng(0)
  for size in args.latent_sizes:
    sample = jnp.asarray(rng.standard_normal((2, size, size, 4)), jnp.float32)
    timesteps = jnp.full((2,), 500)
    context = jnp.asarray(rng.standard_normal((2, 77, 768)), jnp.float32)
    image = jnp.asarray(rng.random((2, 8 * size, 8 * size, 3)), jnp.float32)
    for precision, dtype, stored in (("fp32", jnp.float32, jnp.float32),
                                     ("bf16", jnp.bfloat16, jnp.float32),
                                     ("bf16_weights", jnp.bfloat16, jnp.bfloat16)):
      unet_module = dataclasses.replace(unet, compute_dtype=dtype)
      controlnet_module = dataclasses.replace(controlnet, compute_dtype=dtype)
      cast = lambda params, stored=stored: jax.tree.map(lambda leaf: leaf.astype(stored), params)

      def unet_forward(params, sample, timesteps, context, module=unet_module):
        return module.apply({"params": params}, sample, timesteps, context)

      def controlled_forward(params, sample, timesteps, context, image,
                             unet_module=unet_module, controlnet_module=controlnet_module):
        residuals = controlnet_module.apply({"params": params[1]}, sample, timesteps, context,
                                            image)
        return unet_module.apply({"params": params[0]}, sample, timesteps, context,
                                 control=residuals)

      for model, function, arguments in (
          ("unet", unet_forward, (cast(unet_params), sample, timesteps, context)),
          ("unet_controlnet", controlled_forward,
           (cast((unet_params, controlnet_params)), sample, timesteps, context, image))):
        key = f"{model}_{size}x{size}_{precision}"
        result["models"][key] = profile(jax.jit(function), arguments, args.repeats)
        print(key, result["models"][key]["wall_seconds_per_forward"],
              result["models"][key]["share"], flush=True)
  result["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(RESULTS / f"{args.name}.json", result)
  print(f"profile_diffusion: results in {RESULTS / args.name}.json")


if __name__ == "__main__":
  main()
