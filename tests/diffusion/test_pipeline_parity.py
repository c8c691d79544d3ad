"""The whole ControlNet inpainting pipeline against diffusers' (SD and SDXL), float32.

Tiny random pipelines (every weight perturbed, so zero-initialised layers hide nothing) are
saved with diffusers' `save_pretrained` (safetensors) and loaded through `load_pipeline`. The
reference runs with a seeded torch generator; the same draws, replayed in the order the
reference makes them, are injected into our sampler (`SamplerNoise`).
"""

import dataclasses
import json
import shutil

import jax
import numpy as np
import pytest

from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion import pipeline_components
from signerf_jax.diffusion import sampler
from signerf_jax.errors import InputError

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")
pytestmark = pytest.mark.parity

TOLERANCE = 1e-3
HEIGHT, WIDTH = 32, 48  # Latents of 16 x 24 (the two-block VAE halves the size).
LATENT_FACTOR = 2
PROMPTS = ["a red chair", "A photo of a Bench, in the garden!"]
NEGATIVE_PROMPTS = ["blurry", "low quality"]
SCHEDULER = dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                 clip_sample=False, set_alpha_to_one=False, steps_offset=1)
SCHEDULER_CLASSES = {"ddim": "DDIMScheduler", "dpm_solver_multistep": "DPMSolverMultistepScheduler",
                     "euler_ancestral": "EulerAncestralDiscreteScheduler"}
SD_BACKBONE = dict(block_out_channels=(32, 64), norm_num_groups=8, layers_per_block=1,
                   attention_head_dim=4, cross_attention_dim=32,
                   down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"))
SD_UP_BLOCKS = ("UpBlock2D", "CrossAttnUpBlock2D")
# SDXL-style: text_time conditioning (pooled 16 + 6 time ids x 8), linear projections, two
# transformer layers in the attention block, no attention in the first block.
SDXL_BACKBONE = dict(SD_BACKBONE, down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
                     attention_head_dim=(2, 4), use_linear_projection=True,
                     transformer_layers_per_block=(1, 2), addition_embed_type="text_time",
                     addition_time_embed_dim=8, projection_class_embeddings_input_dim=16 + 6 * 8)
SDXL_UP_BLOCKS = ("CrossAttnUpBlock2D", "UpBlock2D")
CONDITIONING_EMBEDDING = (8, 16)  # Downsamples the control image by 2, the latent factor.

BYTE_SYMBOLS = list(tokenizer_lib.byte_to_symbol().values())
MERGES = [("r", "e</w>"), ("c", "h")]
VOCABULARY = {token: index for index, token in enumerate(
    BYTE_SYMBOLS + [symbol + "</w>" for symbol in BYTE_SYMBOLS] + ["re</w>", "ch"] +
    ["<|startoftext|>", "<|endoftext|>"])}


def reference_tokenizer(directory, pad_token):
  """transformers' CLIPTokenizer on a byte-level vocabulary with two merges."""
  directory.mkdir()
  (directory / "vocab.json").write_text(json.dumps(VOCABULARY, ensure_ascii=False), "utf-8")
  (directory / "merges.txt").write_text(
      "#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in MERGES), "utf-8")
  (directory / "tokenizer_config.json").write_text(
      json.dumps({"model_max_length": 77, "pad_token": pad_token}))
  return transformers.CLIPTokenizer.from_pretrained(str(directory))


def text_encoder(perturb, seed, hidden_size, with_projection=False, hidden_act="quick_gelu"):
  config = transformers.CLIPTextConfig(
      vocab_size=len(VOCABULARY), hidden_size=hidden_size, intermediate_size=37,
      num_hidden_layers=2, num_attention_heads=4, max_position_embeddings=77, projection_dim=16,
      hidden_act=hidden_act, bos_token_id=VOCABULARY["<|startoftext|>"],
      eos_token_id=VOCABULARY["<|endoftext|>"], pad_token_id=1)
  torch.manual_seed(seed)
  model_class = (transformers.CLIPTextModelWithProjection if with_projection
                 else transformers.CLIPTextModel)
  return perturb(model_class(config), seed)


def build_checkpoint(diffusers, perturb, root, sdxl):
  """A saved reference pipeline (inpainting UNet) and a 4-channel UNet saved on its own.

  Every weight is perturbed with `perturb(model, seed)`.

  Returns {"pipeline": directory, "unet_4": directory, "components": the torch modules}.
  """
  backbone, up_blocks = (SDXL_BACKBONE, SDXL_UP_BLOCKS) if sdxl else (SD_BACKBONE, SD_UP_BLOCKS)
  torch.manual_seed(0)
  unets = {channels: perturb(diffusers.UNet2DConditionModel(
      **backbone, up_block_types=up_blocks, in_channels=channels), channels)
           for channels in (9, 4)}
  components = dict(
      unet=unets[9],
      controlnet=perturb(diffusers.ControlNetModel(
          **backbone, conditioning_embedding_out_channels=CONDITIONING_EMBEDDING), 20),
      vae=perturb(diffusers.AutoencoderKL(
          block_out_channels=(32, 64), down_block_types=("DownEncoderBlock2D",) * 2,
          up_block_types=("UpDecoderBlock2D",) * 2, layers_per_block=1, latent_channels=4,
          norm_num_groups=8, scaling_factor=0.5), 21),
      scheduler=diffusers.DDIMScheduler(**SCHEDULER))
  if sdxl:
    components.update(
        text_encoder=text_encoder(perturb, 22, 16),
        tokenizer=reference_tokenizer(root / "vocab", "<|endoftext|>"),
        text_encoder_2=text_encoder(perturb, 23, 16, with_projection=True, hidden_act="gelu"),
        tokenizer_2=reference_tokenizer(root / "vocab_2", "!"))
  else:
    components.update(text_encoder=text_encoder(perturb, 22, 32),
                      tokenizer=reference_tokenizer(root / "vocab", "<|endoftext|>"))
  reference_pipeline(diffusers, components, sdxl).save_pretrained(root / "pipeline",
                                                                  safe_serialization=True)
  unets[4].save_pretrained(root / "unet_4", safe_serialization=True)
  return {"pipeline": root / "pipeline", "unet_4": root / "unet_4", "components": components,
          "unets": unets}


def reference_pipeline(diffusers, components, sdxl, **replace):
  components = {**components, **replace}
  if sdxl:
    return diffusers.StableDiffusionXLControlNetInpaintPipeline(
        **components, add_watermarker=False, requires_aesthetics_score=False,
        force_zeros_for_empty_prompt=True)
  return diffusers.StableDiffusionControlNetInpaintPipeline(
      **components, safety_checker=None, feature_extractor=None, requires_safety_checker=False)


@pytest.fixture(scope="module", autouse=True)
def single_torch_thread():
  """The tiny reference runs ~10x faster on one thread when the cores are shared."""
  threads = torch.get_num_threads()
  torch.set_num_threads(1)
  yield
  torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def checkpoints(diffusers, perturb_parameters, tmp_path_factory):
  return {sdxl: build_checkpoint(diffusers, perturb_parameters,
                                 tmp_path_factory.mktemp("sdxl" if sdxl else "sd"), sdxl)
          for sdxl in (False, True)}


@pytest.fixture(scope="module")
def inputs():
  """Two samples with their own image, soft random mask and control image (numpy, [0, 1])."""
  rng = np.random.default_rng(0)
  return dict(image=rng.random((2, HEIGHT, WIDTH, 3), np.float32),
              mask=rng.random((2, HEIGHT, WIDTH, 1), np.float32),
              control=rng.random((2, HEIGHT, WIDTH, 3), np.float32))


def replayed_noise(seed, num_steps, encodes_image, ancestral):
  """The reference's generator draws, in its order, as our SamplerNoise (NHWC).

  The inpainting pipelines draw: the image's posterior sample (only for strength < 1 or a
  4-channel UNet), the initial noise, the masked image's posterior sample, then one draw per
  step for an ancestral scheduler.
  """
  generator = torch.Generator().manual_seed(seed)
  shape = (2, 4, HEIGHT // LATENT_FACTOR, WIDTH // LATENT_FACTOR)
  draw = lambda: torch.randn(shape, generator=generator).numpy().transpose(0, 2, 3, 1)
  zeros = np.zeros((shape[0], *shape[2:], shape[1]), np.float32)
  image_posterior = draw() if encodes_image else zeros
  latents = draw()
  masked_image_posterior = draw()
  steps = np.stack([draw() if ancestral else zeros for _ in range(num_steps)], axis=1)
  return sampler.SamplerNoise(latents, image_posterior, masked_image_posterior, steps)


def load(checkpoint, unet_channels, scheduler_kind):
  unet = checkpoint["unet_4"] if unet_channels == 4 else None  # A separately stored component.
  return pipeline_lib.load_pipeline(checkpoint["pipeline"], unet=unet,
                                    scheduler_kind=scheduler_kind)


CASES = [
    # (sdxl, UNet input channels, scheduler, steps, options). Between them: both UNet kinds,
    # the three schedulers, strength < 1 (and SDXL's default 0.9999), guidance on and off, guess
    # mode, conditioning scales != 1 and control guidance start and end.
    (False, 9, "dpm_solver_multistep", 4, dict(strength=0.75, guidance_scale=2.5,
                                               controlnet_conditioning_scale=1.3,
                                               guess_mode=True)),
    (False, 4, "euler_ancestral", 3, dict(guidance_scale=4.0, controlnet_conditioning_scale=0.6,
                                          control_guidance_start=0.3, control_guidance_end=0.7)),
    (True, 4, "dpm_solver_multistep", 3, dict(strength=0.9999, guidance_scale=5.0,
                                              controlnet_conditioning_scale=0.8, guess_mode=True,
                                              control_guidance_end=0.7)),
    (True, 9, "ddim", 2, dict(guidance_scale=1.0, controlnet_conditioning_scale=0.5)),
]


def case_id(case):
  sdxl, channels, kind, steps, options = case
  return "-".join([("sdxl" if sdxl else "sd"), f"unet{channels}", kind, f"{steps}steps"] +
                  [f"{name}={value}" for name, value in options.items()])


def run_case(diffusers, checkpoints, inputs, case, seed=0):
  """(our images, the reference's images) for one case."""
  sdxl, channels, kind, steps, options = case
  checkpoint = checkpoints[sdxl]
  # The scheduler as diffusers loads it from the saved directory, as ours does. (From the
  # in-memory config, `from_config` would reset values that were defaults, e.g. the spacing.)
  reference = reference_pipeline(
      diffusers, checkpoint["components"], sdxl, unet=checkpoint["unets"][channels],
      scheduler=getattr(diffusers, SCHEDULER_CLASSES[kind]).from_pretrained(
          checkpoint["pipeline"], subfolder="scheduler"))
  negative = None if sdxl else NEGATIVE_PROMPTS  # SDXL: zeros (force_zeros_for_empty_prompt).
  generation = pipeline_lib.GenerationOptions(num_inference_steps=steps, **options)
  # Every option explicitly: the reference pipelines' defaults differ from ours and each other.
  with torch.no_grad():
    expected = reference(
        prompt=PROMPTS, negative_prompt=negative, image=inputs["image"],
        mask_image=inputs["mask"], control_image=inputs["control"], height=HEIGHT, width=WIDTH,
        generator=torch.Generator().manual_seed(seed), output_type="np",
        **{field: getattr(generation, field) for field in (
            "num_inference_steps", "strength", "guidance_scale", "controlnet_conditioning_scale",
            "control_guidance_start", "control_guidance_end", "guess_mode")}).images

  pipeline = load(checkpoint, channels, kind)
  prompt = pipeline_lib.encode_prompts(pipeline, PROMPTS, negative,
                                       guidance=generation.guidance_scale > 1)
  strength = generation.strength
  noise = replayed_noise(seed, int(steps * strength), channels == 4 or strength < 1,
                         kind == "euler_ancestral")
  ours = pipeline_lib.generate(pipeline, prompt, inputs["image"], inputs["mask"],
                               inputs["control"], noise=noise, options=generation)
  return np.asarray(ours), expected


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_matches_diffusers(diffusers, checkpoints, inputs, case):
  ours, expected = run_case(diffusers, checkpoints, inputs, case)
  assert ours.shape == expected.shape == (2, HEIGHT, WIDTH, 3)
  assert expected.std() > 0.05  # Not a saturated or constant image.
  np.testing.assert_allclose(ours, expected, atol=TOLERANCE, rtol=0)


@pytest.mark.slow
def test_new_prompts_seeds_scales_and_images_reuse_the_compiled_sampler(checkpoints, inputs):
  sdxl, channels, kind, steps, options = CASES[0]
  pipeline = load(checkpoints[sdxl], channels, kind)
  first = pipeline_lib.GenerationOptions(num_inference_steps=steps, **options)
  run = lambda prompts, key, generation, scale_images: pipeline_lib.generate(
      pipeline, pipeline_lib.encode_prompts(pipeline, prompts), inputs["image"] * scale_images,
      inputs["mask"], inputs["control"], key=jax.random.key(key), options=generation)
  baseline = run(PROMPTS, 0, first, 1.0)
  program = sampler.program(pipeline.models)
  cache_size = program._cache_size()  # pylint: disable=protected-access
  second = dataclasses.replace(first, guidance_scale=6.0, controlnet_conditioning_scale=0.3,
                               control_guidance_start=0.0, control_guidance_end=0.5)
  changed = run(["a blue sofa", "a tree"], 1, second, 0.5)
  assert program._cache_size() == cache_size  # pylint: disable=protected-access
  assert np.abs(np.asarray(changed) - np.asarray(baseline)).max() > 1e-2


@pytest.mark.slow
def test_a_batch_of_two_equals_two_single_calls(checkpoints, inputs):
  sdxl, channels, kind, steps, options = CASES[0]
  pipeline = load(checkpoints[sdxl], channels, kind)
  generation = pipeline_lib.GenerationOptions(num_inference_steps=steps, **options)
  prompt = pipeline_lib.encode_prompts(pipeline, PROMPTS, NEGATIVE_PROMPTS)
  keys = jax.random.split(jax.random.key(7), 2)
  batch = pipeline_lib.generate(pipeline, prompt, inputs["image"], inputs["mask"],
                                inputs["control"], key=keys, options=generation)
  for index in range(2):
    row = lambda x: None if x is None else x[index:index + 1]
    single_prompt = jax.tree.map(row, prompt)
    single = pipeline_lib.generate(pipeline, single_prompt, row(inputs["image"]),
                                   row(inputs["mask"]), row(inputs["control"]),
                                   key=keys[index:index + 1], options=generation)
    np.testing.assert_allclose(np.asarray(single[0]), np.asarray(batch[index]), atol=1e-5, rtol=0)


# ----------------------------------------------------------------------------------------------
# Loading.


def test_tokenizer_from_tokenizer_json_matches_transformers(checkpoints):
  """transformers 5 saves only tokenizer.json; the ids must equal the reference's."""
  directory = checkpoints[True]["pipeline"] / "tokenizer_2"
  assert not (directory / "vocab.json").exists()
  ours = tokenizer_lib.load_tokenizer(directory)
  reference = checkpoints[True]["components"]["tokenizer_2"]
  texts = PROMPTS + ["there, the chair!! re re"]
  np.testing.assert_array_equal(
      ours.tokenize(texts),
      reference(texts, padding="max_length", max_length=77, truncation=True).input_ids)


def copy_pipeline(source, destination, drop=(), edit_index=None):
  """A copy of a pipeline directory without the `drop` subfolders and model_index entries."""
  shutil.copytree(source, destination, ignore=shutil.ignore_patterns(*drop))
  index = json.loads((source / pipeline_components.MODEL_INDEX).read_text())
  for name in drop:
    index.pop(name)
  if edit_index:
    edit_index(index)
  (destination / pipeline_components.MODEL_INDEX).write_text(json.dumps(index))
  return destination


@pytest.mark.slow
def test_base_model_with_a_separate_controlnet(checkpoints, tmp_path):
  """A user's usual layout: an inpainting base model and a ControlNet downloaded apart."""
  source = checkpoints[False]["pipeline"]
  base = copy_pipeline(source, tmp_path / "base", drop=("controlnet",))
  without = pipeline_lib.load_pipeline(base, scheduler_kind="ddim")
  assert without.models.controlnet is None
  with_controlnet = pipeline_lib.load_pipeline(base, controlnet=source / "controlnet",
                                               scheduler_kind="ddim")
  expected = pipeline_lib.load_pipeline(source)
  jax.tree.map(np.testing.assert_array_equal, with_controlnet.models, expected.models)
  assert with_controlnet.scheduler == expected.scheduler


def test_components_without_a_pipeline_directory(checkpoints):
  source = checkpoints[True]["pipeline"]
  loaded = pipeline_lib.load_pipeline(**{name: source / name for name in (
      "unet", "vae", "controlnet", "text_encoder_2", "tokenizer_2", "scheduler")})
  assert loaded.is_sdxl and len(loaded.text_encoders) == 1  # Only the second encoder.
  with pytest.raises(InputError, match="missing pipeline component 'vae': no pipeline "
                     "directory was given") as error:
    pipeline_lib.load_pipeline(unet=source / "unet", scheduler=source / "scheduler")
  assert error.value.field == "vae"


@pytest.mark.parametrize("drop, missing", [
    (("vae",), "vae"), (("text_encoder",), "text_encoder"), (("tokenizer",), "tokenizer")])
def test_missing_components_name_what_and_where(checkpoints, tmp_path, drop, missing):
  source = checkpoints[False]["pipeline"]
  broken = copy_pipeline(source, tmp_path / "broken", drop=drop)
  with pytest.raises(InputError, match=f"missing pipeline component '{missing}'.*"
                     "model_index.json does not list it") as error:
    pipeline_lib.load_pipeline(broken)
  assert error.value.field == missing and error.value.path == str(broken)


def test_listed_but_absent_component_and_unsupported_options(checkpoints, tmp_path):
  source = checkpoints[False]["pipeline"]
  broken = copy_pipeline(source, tmp_path / "broken")
  shutil.rmtree(broken / "unet")
  with pytest.raises(InputError, match="component 'unet' not found") as error:
    pipeline_lib.load_pipeline(broken)
  assert error.value.path == str(broken / "unet")
  refiner = copy_pipeline(source, tmp_path / "refiner",
                          edit_index=lambda index: index.update(requires_aesthetics_score=True))
  with pytest.raises(InputError, match="aesthetic-score"):
    pipeline_lib.load_pipeline(refiner)
  with pytest.raises(InputError, match="PNDMScheduler"):
    pndm = copy_pipeline(source, tmp_path / "pndm")
    config = json.loads((pndm / "scheduler" / "scheduler_config.json").read_text())
    config["_class_name"] = "PNDMScheduler"
    (pndm / "scheduler" / "scheduler_config.json").write_text(json.dumps(config))
    pipeline_lib.load_pipeline(pndm)


def test_generate_checks_its_inputs(checkpoints, inputs):
  pipeline = load(checkpoints[False], 9, "ddim")
  prompt = pipeline_lib.encode_prompts(pipeline, PROMPTS)
  with pytest.raises(InputError) as error:
    pipeline_lib.generate(pipeline, prompt, inputs["image"], inputs["mask"][:1],
                          inputs["control"], key=jax.random.key(0))
  assert error.value.field == "mask"
  with pytest.raises(InputError, match="exactly when the pipeline has a ControlNet"):
    pipeline_lib.generate(pipeline, prompt, inputs["image"], inputs["mask"], None,
                          key=jax.random.key(0))
  with pytest.raises(InputError, match="control_guidance_start"):
    pipeline_lib.generate(pipeline, prompt, inputs["image"], inputs["mask"], inputs["control"],
                          key=jax.random.key(0),
                          options=pipeline_lib.GenerationOptions(control_guidance_start=0.5,
                                                                 control_guidance_end=0.5))
