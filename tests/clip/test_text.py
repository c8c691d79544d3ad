"""CLIP text encoders and prompt encoding: parity with transformers and diffusers (float32)."""

import dataclasses
import json
import types

import numpy as np
import pytest
from safetensors import safe_open
from safetensors.numpy import load_file, save_file

from signerf_jax.clip import text as clip_text
from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.errors import InputError

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

pytestmark = pytest.mark.parity

BYTE_SYMBOLS = list(tokenizer_lib.byte_to_symbol().values())
VOCABULARY = {token: index for index, token in enumerate(
    BYTE_SYMBOLS + [symbol + "</w>" for symbol in BYTE_SYMBOLS] + ["<|startoftext|>",
                                                                   "<|endoftext|>"])}
BOS, EOS = VOCABULARY["<|startoftext|>"], VOCABULARY["<|endoftext|>"]
TINY = dict(vocab_size=len(VOCABULARY), hidden_size=32, intermediate_size=37, num_hidden_layers=3,
            num_attention_heads=4, max_position_embeddings=77, projection_dim=16,
            bos_token_id=BOS, eos_token_id=EOS, pad_token_id=1)
TOLERANCE = dict(atol=1e-5, rtol=0)


MODERN_EOS = 7  # An eos id that is not the largest id, so both pooling rules differ.


def random_ids(batch, seed=0):
  """[batch, 77] ids where the first MODERN_EOS and the largest id sit at different positions."""
  rng = np.random.default_rng(seed)
  ids = rng.integers(0, TINY["vocab_size"] - 1, (batch, 77))
  ids[ids == MODERN_EOS] = 3
  for row in range(batch):
    first_eos, largest = rng.choice(np.arange(1, 77), 2, replace=False)
    ids[row, first_eos] = MODERN_EOS
    ids[row, largest] = TINY["vocab_size"] - 1
    ids[row, max(first_eos, largest) + 1:] = MODERN_EOS
  return ids


def save_reference(directory, with_projection, dtype=torch.float32, seed=0, **options):
  """A tiny transformers model with every weight perturbed (so swapped tensors show), saved as
  safetensors; returns the float32 reference holding exactly the saved (rounded) weights."""
  torch.manual_seed(seed)
  config = transformers.CLIPTextConfig(**{**TINY, **options})
  model_class = (transformers.CLIPTextModelWithProjection if with_projection
                 else transformers.CLIPTextModel)
  model = model_class(config).eval()
  with torch.no_grad():
    for parameter in model.parameters():
      parameter.add_(0.1 * torch.randn_like(parameter))
  model.to(dtype).save_pretrained(directory, safe_serialization=True)
  return model.to(dtype).to(torch.float32)


def reference_outputs(model, ids):
  with torch.no_grad():
    ids = torch.from_numpy(ids)
    output = model(ids, output_hidden_states=True)
    text_model = getattr(model, "text_model", model)
    return {"last_hidden_state": output.last_hidden_state.numpy(),
            "hidden_states": [state.numpy() for state in output.hidden_states],
            "pooled_output": text_model(ids).pooler_output.numpy(),
            "text_embeds": output.text_embeds.numpy() if hasattr(output, "text_embeds") else None}


@pytest.mark.slow
@pytest.mark.parametrize("with_projection, hidden_act, eos_token_id", [
    (False, "quick_gelu", 2),  # SD 1.x: legacy config, pooled at argmax(ids).
    (False, "gelu", MODERN_EOS),  # SD 2.x style: pooled at the first eos.
    (True, "gelu", MODERN_EOS),  # SDXL's text_encoder_2.
    (True, "quick_gelu", 2),
])
def test_outputs_match_transformers(tmp_path, with_projection, hidden_act, eos_token_id):
  reference = save_reference(tmp_path, with_projection, hidden_act=hidden_act,
                             eos_token_id=eos_token_id)
  encoder = clip_text.load_text_encoder(tmp_path)
  assert encoder.config.with_projection == with_projection
  ids = random_ids(3)
  # The two pooling conventions pick different tokens here, so using the wrong one would fail.
  assert (np.argmax(ids, -1) != np.argmax(ids == MODERN_EOS, -1)).all()
  expected = reference_outputs(reference, ids)
  output = encoder(ids)
  np.testing.assert_allclose(output.last_hidden_state, expected["last_hidden_state"], **TOLERANCE)
  assert len(output.hidden_states) == TINY["num_hidden_layers"] + 1
  for ours, theirs in zip(output.hidden_states, expected["hidden_states"]):
    np.testing.assert_allclose(ours, theirs, **TOLERANCE)
  np.testing.assert_allclose(output.pooled_output, expected["pooled_output"], **TOLERANCE)
  if with_projection:
    np.testing.assert_allclose(output.text_embeds, expected["text_embeds"], **TOLERANCE)
  else:
    assert output.text_embeds is None


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_checkpoints(tmp_path, dtype):
  reference = save_reference(tmp_path, True, dtype=dtype, hidden_act="gelu")
  with safe_open(tmp_path / "model.safetensors", framework="numpy") as handle:
    stored = {handle.get_slice(name).get_dtype() for name in handle.keys()}
  assert stored == {"F16" if dtype == torch.float16 else "BF16"}
  ids = random_ids(2)
  output = clip_text.load_text_encoder(tmp_path)(ids)
  expected = reference_outputs(reference, ids)
  np.testing.assert_allclose(output.text_embeds, expected["text_embeds"], **TOLERANCE)


def test_prefixed_names_and_position_ids_buffer_load_alike(tmp_path):
  """transformers 4 saved CLIPTextModel under `text_model.` with a position_ids buffer."""
  save_reference(tmp_path / "plain", False)
  (tmp_path / "prefixed").mkdir()
  tensors = load_file(tmp_path / "plain" / "model.safetensors")
  assert not any(name.startswith("text_model.") for name in tensors)
  prefixed = {f"text_model.{name}": value for name, value in tensors.items()}
  prefixed["text_model.embeddings.position_ids"] = np.arange(77)[None]
  save_file(prefixed, tmp_path / "prefixed" / "model.safetensors")
  (tmp_path / "prefixed" / "config.json").write_text(
      (tmp_path / "plain" / "config.json").read_text())
  ids = random_ids(2)
  prefixed_output = clip_text.load_text_encoder(tmp_path / "prefixed")(ids)
  plain_output = clip_text.load_text_encoder(tmp_path / "plain")(ids)
  np.testing.assert_array_equal(prefixed_output.pooled_output, plain_output.pooled_output)


def test_no_recompilation_for_new_ids(tmp_path):
  save_reference(tmp_path, False)
  encoder = clip_text.load_text_encoder(tmp_path)
  encoder(random_ids(2, seed=1))
  cache_size = clip_text.encode._cache_size()  # pylint: disable=protected-access
  encoder(random_ids(2, seed=2))
  assert clip_text.encode._cache_size() == cache_size  # pylint: disable=protected-access


def edit_checkpoint(directory, edit_tensors=None, edit_config=None):
  path = directory / "model.safetensors"
  tensors = load_file(path)
  if edit_tensors:
    edit_tensors(tensors)
  save_file(tensors, path)
  config = json.loads((directory / "config.json").read_text())
  if edit_config:
    edit_config(config)
  (directory / "config.json").write_text(json.dumps(config))


@pytest.mark.parametrize("edit_tensors, edit_config, message", [
    (lambda t: t.pop("text_model.encoder.layers.1.mlp.fc2.bias"), None,
     r"missing tensor text_model.encoder.layers.1.mlp.fc2.bias \(expected shape \(32,\)"),
    (lambda t: t.update(extra=np.zeros(3, np.float32)), None, r"unexpected tensor extra"),
    (None, lambda c: c.update(intermediate_size=40),
     r"fc1.weight has shape \(37, 32\) but the config needs \(40, 32\)"),
    (None, lambda c: c.update(architectures=["CLIPTextModel"]),
     "unexpected tensor text_projection.weight"),
    (None, lambda c: c.update(hidden_act="relu"), "hidden_act 'relu' is not implemented"),
])
def test_checkpoint_errors_name_the_tensor(tmp_path, edit_tensors, edit_config, message):
  save_reference(tmp_path, True)
  edit_checkpoint(tmp_path, edit_tensors, edit_config)
  with pytest.raises(InputError, match=message):
    clip_text.load_text_encoder(tmp_path)


# ----------------------------------------------------------------------------------------------
# Prompt encoding against diffusers' pipelines (their encode_prompt on a stand-in pipeline).


def write_tokenizer(directory, pad_token):
  directory.mkdir()
  (directory / "vocab.json").write_text(json.dumps(VOCABULARY, ensure_ascii=False), "utf-8")
  (directory / "merges.txt").write_text("#version: 0.2\n", "utf-8")
  (directory / "tokenizer_config.json").write_text(
      json.dumps({"model_max_length": 77, "pad_token": pad_token}))
  return directory


@pytest.fixture(scope="module")
def components(tmp_path_factory):
  """SDXL-like pair: (CLIPTextModel, quick_gelu, eos-padded) and (with projection, gelu, "!")."""
  root = tmp_path_factory.mktemp("components")
  references = [save_reference(root / "text_encoder", False, eos_token_id=2),
                save_reference(root / "text_encoder_2", True, seed=1, hidden_act="gelu",
                               eos_token_id=EOS, hidden_size=24, num_attention_heads=3)]
  tokenizer_directories = [write_tokenizer(root / "tokenizer", "<|endoftext|>"),
                           write_tokenizer(root / "tokenizer_2", "!")]
  return {
      "references": references,
      "reference_tokenizers": [transformers.CLIPTokenizer.from_pretrained(str(directory))
                               for directory in tokenizer_directories],
      "encoders": [clip_text.load_text_encoder(root / "text_encoder"),
                   clip_text.load_text_encoder(root / "text_encoder_2")],
      "tokenizers": [tokenizer_lib.load_tokenizer(directory)
                     for directory in tokenizer_directories],
  }


PROMPTS = ["a red chair", "A photo of a Chair, in the garden!"]


@pytest.mark.parametrize("negative_prompts", [None, ["blurry", "low quality, ugly"]])
@pytest.mark.parametrize("second", [False, True])  # SD 1.x-like or SD 2.x-like encoder.
def test_encode_prompt_matches_diffusers(components, negative_prompts, second):
  diffusers = pytest.importorskip("diffusers")
  index = int(second)
  reference = components["references"][index]
  pipeline = types.SimpleNamespace(tokenizer=components["reference_tokenizers"][index],
                                   text_encoder=getattr(reference, "text_model", reference))
  with torch.no_grad():
    expected = diffusers.StableDiffusionControlNetInpaintPipeline.encode_prompt(
        pipeline, PROMPTS, torch.device("cpu"), 1, True, negative_prompts)
  ours = clip_text.encode_prompt(components["tokenizers"][index], components["encoders"][index],
                                 PROMPTS, negative_prompts)
  np.testing.assert_allclose(ours.prompt_embeds, expected[0].numpy(), **TOLERANCE)
  np.testing.assert_allclose(ours.negative_prompt_embeds, expected[1].numpy(), **TOLERANCE)
  assert clip_text.encode_prompt(components["tokenizers"][index], components["encoders"][index],
                                 PROMPTS, guidance=False).negative_prompt_embeds is None


@pytest.mark.parametrize("negative_prompts, negative_prompts_2, force_zeros", [
    (None, None, True),  # SDXL base: zero unconditional embeddings.
    (None, None, False),  # Empty-prompt unconditional embeddings.
    (["blurry", "dark"], None, True),
    (["blurry", "dark"], ["grainy", "noisy!"], False),
])
def test_encode_prompt_sdxl_matches_diffusers(components, negative_prompts, negative_prompts_2,
                                              force_zeros):
  diffusers = pytest.importorskip("diffusers")
  tokenizer, tokenizer_2 = components["reference_tokenizers"]
  text_encoder, text_encoder_2 = components["references"]
  pipeline = types.SimpleNamespace(
      tokenizer=tokenizer, tokenizer_2=tokenizer_2, text_encoder=text_encoder,
      text_encoder_2=text_encoder_2,
      config=types.SimpleNamespace(force_zeros_for_empty_prompt=force_zeros))
  prompts_2 = ["a chair", "a bench by the sea"]
  with torch.no_grad():
    expected = diffusers.StableDiffusionXLControlNetInpaintPipeline.encode_prompt(
        pipeline, PROMPTS, prompts_2, torch.device("cpu"), 1, True, negative_prompts,
        negative_prompts_2)
  ours = clip_text.encode_prompt_sdxl(components["tokenizers"], components["encoders"], PROMPTS,
                                      prompts_2, negative_prompts, negative_prompts_2,
                                      force_zeros_for_empty_prompt=force_zeros)
  assert ours.prompt_embeds.shape == (2, 77, 32 + 24)
  for name, value in zip(dataclasses.fields(ours), expected):
    np.testing.assert_allclose(getattr(ours, name.name), value.numpy(), **TOLERANCE,
                               err_msg=name.name)
  if force_zeros and negative_prompts is None:
    assert not np.any(ours.negative_prompt_embeds)
