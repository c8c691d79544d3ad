"""Where the UNet's (and UNet + ControlNet's) forward time goes on this CPU, by kind of work.

  python experiments/profile_diffusion.py [--latent_sizes 32 64] [--repeats 3]
      [--parts operations components] [--name profile_diffusion]

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
op_name.

Under the float32 sampler's compiler options (`sampler.CPU_FLOAT32_COMPILER_OPTIONS`, what
bench_diffusion times) XLA's own matmuls run outside the profiler's view, so a second part,
"components", breaks the fp32 UNet's forward down bottom-up instead: the forward compiled with
those options, and each level's Transformer2D block and its self-attention (projections
included), cross-attention and feed-forward alone at that level's shapes, each with its nominal
GFLOP and GFLOP/s; the transformers' share is their seconds times their count in the UNet over
the forward's, and "rest" (resnets, samplers, embeddings) what the forward takes beyond them.
All are timed round by round (one call of each per round; medians).
Writes <name>.json with the machine and its load into --results DIR (default
outputs/experiments/).
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

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax.profiler import ProfileData

from signerf_jax import files
from signerf_jax.diffusion import model_configs, weights
from signerf_jax.diffusion.attention import Attention, GEGLUFeedForward, Transformer2D
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.unet import UNet2DCondition

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position
from bench_attention import alternate, compiled  # pylint: disable=wrong-import-position
from bench_diffusion import SD15_UNET  # pylint: disable=wrong-import-position

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


def operations_part(sizes: list[int], repeats: int) -> dict[str, Any]:
  """The profiled breakdown (`profile`) of each model and precision at each latent size."""
  results = {}
  unet = UNet2DCondition(model_configs.UNetConfig.from_dict(SD15_UNET))
  controlnet = ControlNet(model_configs.ControlNetConfig.from_dict(
      {**{name: value for name, value in SD15_UNET.items() if name != "sample_size"},
       "conditioning_channels": 3}))
  unet_params, controlnet_params = weights.random_params(unet), weights.random_params(controlnet)
  rng = np.random.default_rng(0)
  for size in sizes:
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
        results[key] = profile(jax.jit(function), arguments, repeats)
        print(key, results[key]["wall_seconds_per_forward"], results[key]["share"], flush=True)
  return results


def compiled_forward(module: nn.Module, arguments: tuple[jax.Array, ...]):
  """A call of `module`'s forward (random parameters) on `arguments`, compiled as the float32
  sampler is."""
  params = module.init(jax.random.key(0), *arguments)
  forward = compiled(module.apply, (params, *arguments))
  return lambda _: forward(params, *arguments)


def transformers_per_level(config: model_configs.UNetConfig) -> list[int]:
  """How many Transformer2D blocks the UNet runs at each level (resolution): one per layer of a
  cross-attention down block, one per layer of an up block (one more layer than down), and one
  in a cross-attention middle block (at the lowest resolution)."""
  up_block_types = config.up_block_types[::-1]  # Per level, as the down blocks.
  last = len(config.block_out_channels) - 1
  return [layers * config.down_block_types[level].startswith("CrossAttn")
          + (layers + 1) * up_block_types[level].startswith("CrossAttn")
          + int(level == last and config.mid_block_type == model_configs.CROSS_ATTENTION_MID)
          for level, layers in enumerate(config.layers_per_block)]


def components_part(sizes: list[int], repeats: int) -> dict[str, Any]:
  """The bottom-up breakdown of the fp32 UNet's forward (module docstring), batch 2."""
  config = model_configs.UNetConfig.from_dict(SD15_UNET)
  text_tokens, text_features = 77, config.cross_attention_dim
  rng = np.random.default_rng(0)
  normal = lambda *shape: jnp.asarray(rng.standard_normal(shape), jnp.float32)
  context = normal(2, text_tokens, text_features)
  results = {}
  for size in sizes:
    calls = {"forward": compiled_forward(UNet2DCondition(config), (
        normal(2, size, size, 4), jnp.full((2,), 500), context))}
    counts, gflop = {}, {}
    for level, (channels, count) in enumerate(zip(config.block_out_channels,
                                                  transformers_per_level(config))):
      if not count:
        continue
      side, heads = size // 2**level, config.num_attention_heads[level]
      layers = config.transformer_layers_per_block[level]  # Blocks of the three parts each.
      tokens, head_dim = 2 * side * side, channels // heads
      x = normal(2, side, side, channels)
      sequence = x.reshape(2, side * side, channels)
      level_name = f"level_{level}_{side}x{side}x{channels}"
      counts[level_name] = count
      gflop[level_name] = {  # Nominal: matmul multiply-adds x 2.
          "self_attention": (8 * tokens * channels**2 + 4 * tokens * side * side * channels) / 1e9,
          "cross_attention": (4 * tokens * channels**2 + 8 * text_tokens * text_features * channels
                              + 4 * tokens * text_tokens * channels) / 1e9,
          "feed_forward": 24 * tokens * channels**2 / 1e9}
      gflop[level_name]["transformer"] = (layers * sum(gflop[level_name].values())
                                          + 4 * tokens * channels**2 / 1e9)
      for name, (module, arguments) in {
          "self_attention": (Attention(heads, head_dim, channels), (sequence,)),
          "cross_attention": (Attention(heads, head_dim, channels), (sequence, context)),
          "feed_forward": (GEGLUFeedForward(channels), (sequence,)),
          "transformer": (Transformer2D(heads, head_dim, layers, config.norm_num_groups,
                                        config.use_linear_projection),
                          (x, context))}.items():
        calls[f"{level_name}/{name}"] = compiled_forward(module, arguments)
    # Round by round, so that a slow spell of a shared machine slows every part alike.
    seconds = {name: measured["median_seconds"]
               for name, measured in alternate(calls, "forward", repeats).items()}
    transformers = sum(count * seconds[f"{level_name}/transformer"]
                       for level_name, count in counts.items())
    results[f"unet_{size}x{size}_fp32"] = {
        "forward_seconds": round(seconds["forward"], 4),
        "transformers_seconds": round(transformers, 4),
        "transformers_share": round(transformers / seconds["forward"], 3),
        "rest_seconds": round(seconds["forward"] - transformers, 4),
        "levels": {level_name: {
            "transformers_in_unet": count,
            **{name: {"seconds": round(seconds[f"{level_name}/{name}"], 5),
                      "gflop": round(nominal, 2),
                      "gflops_per_second": round(nominal / seconds[f"{level_name}/{name}"], 1)}
               for name, nominal in gflop[level_name].items()}}
                   for level_name, count in counts.items()}}
    print(size, results[f"unet_{size}x{size}_fp32"], flush=True)
  return results


PARTS = ("operations", "components")


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--latent_sizes", type=int, nargs="+", default=[32, 64])
  parser.add_argument("--repeats", type=int, default=3,
                      help="timed and profiled forwards per model and precision")
  parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
  parser.add_argument("--name", default="profile_diffusion", help="results/<name>.json")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  result: dict[str, Any] = {"machine": machine.record(), "repeats": args.repeats}
  if "operations" in args.parts:
    result["models"] = operations_part(args.latent_sizes, args.repeats)
  if "components" in args.parts:
    result["components"] = components_part(args.latent_sizes, args.repeats)
  result["machine"]["load_average_at_end"] = os.getloadavg()
  files.write_json(args.results / f"{args.name}.json", result)
  print(f"profile_diffusion: results in {args.results / args.name}.json")


if __name__ == "__main__":
  main()
