"""What an edit costs at the paper's settings on a GPU or a TPU, on paper: FLOPs and memory of
each stage's programs counted by XLA, and the time they would take at a share of a device's peak.

    python experiments/edit_cost.py [--views 100] [--preview_sheets 4] [--utilisation 0.4]
        [--nerf_data ../shared/data/stitch --nerf_downscale 4]

Nothing runs on an accelerator, and nothing is allocated for the diffusion models: their programs
are lowered on abstract shapes (`jax.ShapeDtypeStruct`) and counted by XLA's cost analysis
(`Lowered.cost_analysis`: FLOPs, two per multiply-add, elementwise operations included) and, on
the program XLA:CPU compiles, its memory plan (`Compiled.memory_analysis`: arguments and
temporaries) and the bytes its fused operations access (a GPU's or TPU's compiler fuses and plans
its own buffers, so these are estimates). The programs are traced as GPUs
and TPUs run them: XLA's convolutions and `jax.nn.dot_product_attention`
(`layers.backend_or_default` reads `jax.default_backend()`, made to answer "gpu" while tracing).
XLA counts a loop's body once, so FLOPs are counted on loop-free programs (attention over all
queries at once, one image per VAE call); memory on the programs as they run (attention over
chunks of `AttentionOptions.query_chunk_size` queries).

The shapes: SD 1.5's inpainting UNet (9 input channels) with a depth ControlNet, SD 1.5's VAE,
the paper's 2 x 3 sheet of 512-px tiles (1,024 x 1,536 px, latents 128 x 192), classifier-free
guidance (batch 2), 77 text tokens, bfloat16 weights and compute. Each candidate sheet of the
preview and each view of the image set update samples one whole sheet: `steps` denoising steps
of UNet + ControlNet, one VAE encoding (the masked image; two from below strength 1) and one
decoding. The NeRF step is the one `signerf train` compiles for `--nerf_data` (skipped when
absent); its FLOPs and bytes do not depend on the image count, its memory does (the images live
on the device); its loops (random bits, small per-ray searches) are a negligible share. The
text encoder (about 0.04 TFLOP a prompt pair) and the renders of the views and reference stages
are left out. A cross-check: the UNet's count at 64 x 64 latents against
torch's in results/bench_diffusion.json.

Writes edit_cost.json into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
from pathlib import Path
from typing import Any, Callable
from unittest import mock

import jax
import jax.numpy as jnp

from signerf_jax import files, parallel
from signerf_jax.data import load
from signerf_jax.diffusion import model_configs
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.controlnet import ControlNet
from signerf_jax.diffusion.unet import UNet2DCondition
from signerf_jax.diffusion.vae import AutoencoderKL
from signerf_jax.nerf import train, training_data, training_run

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position
from bench_diffusion import SD15_UNET  # pylint: disable=wrong-import-position

SD15_VAE = {"block_out_channels": (128, 256, 512, 512), "layers_per_block": 2,
            "down_block_types": ("DownEncoderBlock2D",) * 4,
            "up_block_types": ("UpDecoderBlock2D",) * 4, "sample_size": 512}
SHEET_PIXELS = (1024, 1536)  # The paper's 2 x 3 sheet of 512-px tiles (height, width).
LATENT_FACTOR = 8
TEXT_TOKENS, TEXT_WIDTH = 77, 768
# Attention over all queries at once: no loop, so XLA's count covers every query.
WHOLE_ATTENTION = AttentionOptions(query_chunk_size=2**31, key_chunk_size=2**31)
# Peak dense bfloat16 matmul rate (TFLOP/s), memory (GB) and its bandwidth (TB/s), from the
# vendors' data sheets: A100 SXM 80 GB, H100 SXM, one TPU v5e chip.
DEVICES = {"NVIDIA A100 80 GB": (312.0, 80.0, 2.04), "NVIDIA H100 SXM": (989.0, 80.0, 3.35),
           "TPU v5e chip": (197.0, 16.0, 0.82)}


@contextlib.contextmanager
def traced_for(backend: str):
  """Traces programs as on `backend` (its convolution and attention choices)."""
  with mock.patch.object(jax, "default_backend", lambda: backend):
    yield


def abstract(tree, dtype=None):
  """ShapeDtypeStructs of `tree`'s arrays (floating ones cast to `dtype` when given)."""
  def one(leaf):
    floating = jnp.issubdtype(leaf.dtype, jnp.floating)
    return jax.ShapeDtypeStruct(leaf.shape, dtype if dtype and floating else leaf.dtype)
  return jax.tree.map(one, tree)


def abstract_params(module, dtype) -> Any:
  """The module's parameters as ShapeDtypeStructs of `dtype` (from `init` on abstract inputs)."""
  variables = jax.eval_shape(lambda inputs: module.init(jax.random.key(0), **inputs),
                             module.example_inputs())
  return abstract(variables["params"], dtype)


def count(function: Callable, arguments: tuple, memory: bool) -> dict[str, Any]:
  """XLA's counts of `function` on abstract `arguments`: the lowered program's FLOPs and its
  loops (`while_loops`: their bodies count once); with `memory`, the compiled program's
  argument and temporary bytes and the bytes its operations access (after XLA:CPU's fusion:
  each fused operation's inputs and outputs, once)."""
  lowered = jax.jit(function).lower(*arguments)
  result = {"tflop": lowered.cost_analysis()["flops"] / 1e12,
            "while_loops": lowered.as_text().count("stablehlo.while")}
  if memory:
    compiled = lowered.compile()
    plan = compiled.memory_analysis()
    result.update(arguments_gb=plan.argument_size_in_bytes / 1e9,
                  temporaries_gb=plan.temp_size_in_bytes / 1e9,
                  bytes_accessed_gb=compiled.cost_analysis()["bytes accessed"] / 1e9)
  return result


@dataclasses.dataclass(frozen=True)
class DiffusionShapes:
  """SD 1.5's networks for one attention setting, and the inputs of a sheet's programs."""

  attention: AttentionOptions
  dtype: Any = jnp.bfloat16

  def networks(self, unet_channels: int = 9):
    config = dict(SD15_UNET, in_channels=unet_channels)
    unet = UNet2DCondition(model_configs.UNetConfig.from_dict(config), self.attention,
                           self.dtype)
    # A ControlNet copies the UNet's encoder half (diffusers' `ControlNetModel.from_unet`).
    backbone = {name: value for name, value in SD15_UNET.items() if name != "sample_size"}
    controlnet = ControlNet(model_configs.ControlNetConfig.from_dict(backbone), self.attention,
                            self.dtype)
    vae = AutoencoderKL(model_configs.AutoencoderConfig.from_dict(SD15_VAE), self.attention,
                        self.dtype)
    return unet, controlnet, vae

  def latents(self, channels: int, batch: int, size=None) -> jax.ShapeDtypeStruct:
    height, width = size or (SHEET_PIXELS[0] // LATENT_FACTOR, SHEET_PIXELS[1] // LATENT_FACTOR)
    return jax.ShapeDtypeStruct((batch, height, width, channels), self.dtype)

  def text(self, batch: int) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct((batch, TEXT_TOKENS, TEXT_WIDTH), self.dtype)


def denoising_step(shapes: DiffusionShapes, memory: bool) -> dict[str, Any]:
  """One guided step at the sheet's size: ControlNet then the inpainting UNet, batch 2."""
  unet, controlnet, _ = shapes.networks()

  def step(params, latents, inpainting, text, control):
    residuals = controlnet.apply({"params": params[1]}, latents, jnp.ones((2,)), text, control)
    return unet.apply({"params": params[0]}, jnp.concatenate([latents, inpainting], -1),
                      jnp.ones((2,)), text, control=residuals)

  params = (abstract_params(unet, shapes.dtype), abstract_params(controlnet, shapes.dtype))
  control = jax.ShapeDtypeStruct((2, *SHEET_PIXELS, 3), shapes.dtype)
  return count(step, (params, shapes.latents(4, 2), shapes.latents(5, 2), shapes.text(2),
                      control), memory)


def vae_passes(shapes: DiffusionShapes, memory: bool) -> dict[str, dict[str, Any]]:
  """The VAE's encoder on one sheet image and its decoder on one sheet's latents."""
  _, _, vae = shapes.networks()
  params = abstract_params(vae, shapes.dtype)
  image = jax.ShapeDtypeStruct((1, *SHEET_PIXELS, 3), shapes.dtype)
  encode = lambda p, x: vae.apply({"params": p}, x, method=vae.encode).mean
  decode = lambda p, z: vae.apply({"params": p}, z, method=vae.decode)
  return {"vae_encode": count(encode, (params, image), memory),
          "vae_decode": count(decode, (params, shapes.latents(4, 1)), memory)}


def unet_cross_check(bench_results: Path) -> dict[str, Any]:
  """XLA's count of the 4-channel UNet at 64 x 64 latents, batch 2, against torch's count of the
  same forward in bench_diffusion.json."""
  shapes = DiffusionShapes(WHOLE_ATTENTION, jnp.float32)
  unet, _, _ = shapes.networks(unet_channels=4)
  forward = lambda p, x, t: unet.apply({"params": p}, x, jnp.ones((2,)), t)
  counted = count(forward, (abstract_params(unet, jnp.float32),
                            shapes.latents(4, 2, (64, 64)), shapes.text(2)), memory=False)
  torch_tflop = files.read_json(bench_results)["unet_64x64"]["gflop"] / 1e3
  return {"xla_tflop": counted["tflop"], "torch_tflop_in_bench_diffusion": torch_tflop,
          "ratio": counted["tflop"] / torch_tflop}


def nerf_step(data: Path, downscale: int) -> dict[str, Any]:
  """One training step of the NeRF `signerf train` sizes for the dataset at `data`."""
  dataset = load.load_dataset(data, downscale=downscale)
  model = training_run.build_model(dataset)
  config = train.TrainConfig()
  state = jax.eval_shape(lambda: train.init_state(model, config))
  images = abstract(training_data.TrainingData.from_dataset(dataset))
  mesh = parallel.device_mesh()
  step = lambda s, d, p: train.train_step(model, config, s, d, p, mesh)
  counted = count(step, (state, images, jax.ShapeDtypeStruct((), jnp.float32)), memory=True)
  return {"data": str(data), "downscale": downscale, "views": dataset.num_images,
          "image_size": [dataset.width, dataset.height], "sampler": model.capacity.sampler,
          "rays_per_batch": model.capacity.rays_per_batch, **counted}


def stage_costs(programs: dict[str, Any], args) -> dict[str, dict[str, float]]:
  """TFLOP and peak memory (GB) of each stage of an edit: a sheet is `args.steps` denoising
  steps, its VAE encodings and a decoding; the preview samples `preview_sheets` of them, the
  update one per view; the NeRF trainings run their steps. Peak memory: the program's
  arguments (weights, inputs) and temporaries, the largest program of the stage."""
  step, encode, decode = (programs[name] for name in ("denoising_step", "vae_encode",
                                                      "vae_decode"))
  sheet = args.steps * step["tflop"] + args.encodings * encode["tflop"] + decode["tflop"]
  # The UNet, ControlNet and VAE weights (the arguments, with the small inputs) stay on the
  # device through a sheet's program; the three parts' temporaries do not overlap.
  diffusion_memory = (sum(program["arguments_gb"] for program in (step, encode, decode))
                      + max(program["temporaries_gb"] for program in (step, encode, decode)))
  stages = {"preview": {"sheets": args.preview_sheets, "tflop": args.preview_sheets * sheet,
                        "peak_memory_gb": diffusion_memory},
            "update": {"sheets": args.views, "tflop": args.views * sheet,
                       "peak_memory_gb": diffusion_memory}}
  nerf = programs.get("nerf_step")
  if nerf:
    for name, steps in (("original_nerf", args.original_steps),
                        ("nerf_update", args.update_steps)):
      stages[name] = {"steps": steps, "tflop": steps * nerf["tflop"],
                      "bytes_accessed_tb": steps * nerf["bytes_accessed_gb"] / 1e3,
                      "peak_memory_gb": nerf["arguments_gb"] + nerf["temporaries_gb"]}
  return stages


def expected_seconds(stages: dict[str, dict[str, float]], utilisation: float
                     ) -> dict[str, dict[str, float]]:
  """Seconds per stage and device: diffusion stages at `utilisation` of the bfloat16 peak; NeRF
  stages as a lower bound, the larger of FLOPs at the full peak and bytes at the full memory
  bandwidth (hash-table gathers run well below both)."""
  seconds = {}
  for device, (peak_tflops, _, bandwidth_tb) in DEVICES.items():
    seconds[device] = {
        name: (stage["tflop"] / (peak_tflops * utilisation) if "bytes_accessed_tb" not in stage
               else max(stage["tflop"] / peak_tflops, stage["bytes_accessed_tb"] / bandwidth_tb))
        for name, stage in stages.items()}
  return seconds


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--views", type=int, default=100, help="dataset views the update edits")
  parser.add_argument("--preview_sheets", type=int, default=4, help="candidate sheets")
  parser.add_argument("--steps", type=int, default=20,
                      help="denoising steps run (GenerationOptions: 20 at strength 1)")
  parser.add_argument("--encodings", type=int, default=1,
                      help="VAE encodings a sheet (1 at strength 1, 2 below)")
  parser.add_argument("--original_steps", type=int, default=30000)
  parser.add_argument("--update_steps", type=int, default=30000,
                      help="the NeRF update's steps (retrain 30,000, fine-tune 5,000)")
  parser.add_argument("--utilisation", type=float, default=0.4,
                      help="assumed share of the bfloat16 peak the diffusion programs reach")
  parser.add_argument("--nerf_data", default="../shared/data/stitch")
  parser.add_argument("--nerf_downscale", type=int, default=4)
  results_dir.add_argument(parser)
  args = parser.parse_args(argv)
  result: dict[str, Any] = {"machine": machine.record(), "settings": vars(args) | {
      "results": str(args.results)}, "devices": {
          name: {"bfloat16_tflops": peak, "memory_gb": memory, "bandwidth_tb_per_s": bandwidth}
          for name, (peak, memory, bandwidth) in DEVICES.items()}}
  with traced_for("gpu"):
    programs = {"denoising_step": denoising_step(DiffusionShapes(WHOLE_ATTENTION), False)}
    programs.update(vae_passes(DiffusionShapes(WHOLE_ATTENTION), False))
    planned = {"denoising_step": denoising_step(DiffusionShapes(AttentionOptions()), True),
               **vae_passes(DiffusionShapes(AttentionOptions()), True)}
    for name, plan in planned.items():
      programs[name].update({key: plan[key] for key in ("arguments_gb", "temporaries_gb",
                                                         "bytes_accessed_gb")})
    result["unet_cross_check"] = unet_cross_check(
        Path(__file__).resolve().parent / "results" / "bench_diffusion.json")
  if Path(args.nerf_data).is_dir():
    # Resolved: a relative Blender-format dataset root fails load_dataset's containment check.
    programs["nerf_step"] = nerf_step(Path(args.nerf_data).resolve(), args.nerf_downscale)
  result["programs"] = programs
  result["stages"] = stage_costs(programs, args)
  result["expected_seconds"] = expected_seconds(result["stages"], args.utilisation)
  output = Path(args.results) / "edit_cost.json"
  files.write_json(output, result)
  for name, stage in result["stages"].items():
    print(f"edit_cost: {name}: {stage['tflop']:.1f} TFLOP, {stage['peak_memory_gb']:.1f} GB; "
          + ", ".join(f"{device} {seconds[name]:.0f} s"
                      for device, seconds in result["expected_seconds"].items()))
  print(f"edit_cost: -> {output}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
