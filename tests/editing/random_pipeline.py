"""A random-weight ControlNet inpainting pipeline in diffusers layout, written without PyTorch.

The editing tests need a real pipeline directory that `diffusion.pipeline.load_pipeline` reads
exactly as it reads the shipped model or a Stable Diffusion checkpoint; only the weights are
random (outputs are noise, the plumbing is real). The components follow the default model's
architecture (`default_model.model.Architecture`), shrunk: every tensor the loaders expect is
drawn with the scale `diffusion.weights.random_params` uses, so activations stay finite.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

from signerf_jax import files
from signerf_jax.clip import text as clip_text
from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import model as model_lib
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion import weights

# Two denoising steps with guidance: every code path of the sampler, at little cost.
TINY_OPTIONS = pipeline_lib.GenerationOptions(num_inference_steps=2, guidance_scale=3.0)

TINY_ARCHITECTURE = model_lib.Architecture(
    vae_block_out_channels=(8, 16), vae_norm_groups=4, unet_block_out_channels=(16,),
    attention_heads=2, norm_groups=8, conditioning_embedding_channels=(8, 16),
    text_hidden_size=16, text_layers=1, text_heads=2, text_intermediate_size=32)
WORDS = ["a red cow", "a blue striped teapot", "a green box"]


def _random_tensors(shapes: dict[str, tuple[int, ...]], rng: np.random.Generator
                    ) -> dict[str, np.ndarray]:
  tensors = {}
  for name, shape in shapes.items():
    noise = rng.standard_normal(shape).astype(np.float32)
    if name.endswith("weight") and len(shape) >= 2:
      tensors[name] = noise / np.float32(np.sqrt(np.prod(shape[1:])))  # torch layout: fan-in
    elif name.endswith("weight"):
      tensors[name] = 1 + np.float32(0.1) * noise  # norm scales
    else:
      tensors[name] = np.float32(0.1) * noise
  return tensors


def write_random_pipeline(directory: str | Path, architecture: model_lib.Architecture
                          = TINY_ARCHITECTURE, seed: int = 0) -> Path:
  """Writes model_index.json and the unet, controlnet, vae, text_encoder, tokenizer and
  scheduler folders of a random pipeline to `directory`; returns it."""
  directory = Path(directory)
  rng = np.random.default_rng(seed)
  tokenizer = word_tokenizer.WordTokenizer.from_words(WORDS, architecture.max_text_length)
  tokenizer.save(directory / "tokenizer")
  text_config = architecture.text_encoder_config(tokenizer.vocab_size)
  files.write_json(directory / "text_encoder" / "config.json", text_config)
  parsed_text_config = clip_text.CLIPTextConfig.from_dict(text_config, "text_encoder")
  save_file(_random_tensors(clip_text.expected_shapes(parsed_text_config, ""), rng),
            str(directory / "text_encoder" / "model.safetensors"))
  components = model_lib.build(architecture, tokenizer.vocab_size)
  for name, module, config in (("vae", components.vae, architecture.vae_config()),
                               ("unet", components.unet, architecture.unet_config()),
                               ("controlnet", components.controlnet,
                                architecture.controlnet_config())):
    files.write_json(directory / name / "config.json", config)
    save_file(_random_tensors(weights.expected_shapes(module), rng),
              str(directory / name / "diffusion_pytorch_model.safetensors"))
  files.write_json(directory / "scheduler" / "scheduler_config.json",
                   architecture.scheduler_config())
  files.write_json(directory / "model_index.json", {
      "_class_name": "StableDiffusionControlNetInpaintPipeline",
      "_diffusers_version": model_lib.DIFFUSERS_VERSION,
      "unet": ["diffusers", "UNet2DConditionModel"],
      "controlnet": ["diffusers", "ControlNetModel"],
      "vae": ["diffusers", "AutoencoderKL"],
      "text_encoder": ["transformers", "CLIPTextModel"],
      "tokenizer": ["signerf_jax", word_tokenizer.TOKENIZER_CLASS],
      "scheduler": ["diffusers", architecture.scheduler_class],
  })
  return directory


def with_sizes(**changes) -> model_lib.Architecture:
  """TINY_ARCHITECTURE with some fields changed."""
  return dataclasses.replace(TINY_ARCHITECTURE, **changes)
