"""CLIP image preprocessing, image tower and directional similarity: parity with transformers
(and Pillow) on tiny random models whose every weight is perturbed."""

import json

import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

from signerf_jax.clip import preprocessing as clip_preprocessing
from signerf_jax.clip import similarity as clip_similarity
from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.clip import vision as clip_vision
from signerf_jax.errors import InputError

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")
PIL = pytest.importorskip("PIL")
from PIL import Image as PIL_Image  # pylint: disable=g-import-not-at-top,wrong-import-position

pytestmark = pytest.mark.parity

TOLERANCE = dict(atol=1e-5, rtol=0)
BYTE_SYMBOLS = list(tokenizer_lib.byte_to_symbol().values())
VOCABULARY = {token: index for index, token in enumerate(
    BYTE_SYMBOLS + [symbol + "</w>" for symbol in BYTE_SYMBOLS] + ["<|startoftext|>",
                                                                   "<|endoftext|>"])}
IMAGE_SIZE = 32
TINY_VISION = dict(hidden_size=24, intermediate_size=29, num_hidden_layers=2,
                   num_attention_heads=3, image_size=IMAGE_SIZE, patch_size=8)
TINY_TEXT = dict(vocab_size=len(VOCABULARY), hidden_size=32, intermediate_size=37,
                 num_hidden_layers=2, num_attention_heads=4,
                 bos_token_id=VOCABULARY["<|startoftext|>"],
                 eos_token_id=VOCABULARY["<|endoftext|>"], pad_token_id=VOCABULARY["<|endoftext|>"])
PREPROCESSOR = {"size": {"shortest_edge": IMAGE_SIZE},
                "crop_size": {"height": IMAGE_SIZE, "width": IMAGE_SIZE}, "resample": 3}
CAPTIONS = ["a photo of a grey stone statue", "a photo of a bear made of gold, in the park"]


def perturbed(model, seed):
  generator = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for parameter in model.parameters():
      parameter.add_(0.1 * torch.randn(parameter.shape, generator=generator))
  return model.eval()


def write_tokenizer_and_processor(directory):
  (directory / "vocab.json").write_text(json.dumps(VOCABULARY, ensure_ascii=False), "utf-8")
  (directory / "merges.txt").write_text("#version: 0.2\n", "utf-8")
  (directory / "preprocessor_config.json").write_text(json.dumps(PREPROCESSOR))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
  """(torch CLIPModel, its directory with tokenizer and preprocessor files)."""
  directory = tmp_path_factory.mktemp("clip")
  torch.manual_seed(0)
  config = transformers.CLIPConfig(text_config=TINY_TEXT, vision_config=TINY_VISION,
                                   projection_dim=16)
  model = perturbed(transformers.CLIPModel(config), seed=0)
  model.save_pretrained(directory, safe_serialization=True)
  write_tokenizer_and_processor(directory)
  return model, directory


@pytest.fixture(scope="module")
def model(reference):
  return clip_similarity.load_clip_model(reference[1], batch_size=4)


def smooth_images(count, height, width, seed=0):
  """uint8 images with structure at several scales (random noise alone resamples trivially)."""
  rng = np.random.default_rng(seed)
  coarse = rng.uniform(0, 255, (count, height // 4 + 1, width // 4 + 1, 3))
  images = np.repeat(np.repeat(coarse, 4, axis=1), 4, axis=2)[:, :height, :width]
  return np.clip(images + rng.normal(0, 20, images.shape), 0, 255).astype(np.uint8)


def torch_features(output):
  """transformers 5 returns model outputs from get_*_features, older versions tensors."""
  return getattr(output, "pooler_output", output).numpy()


def reference_embeddings(reference_model, directory, images, texts):
  processor = transformers.CLIPImageProcessorPil(**PREPROCESSOR)
  tokenizer = transformers.CLIPTokenizer.from_pretrained(str(directory))
  pixels = processor(images=list(images), return_tensors="pt")["pixel_values"]
  ids = tokenizer(texts, padding="max_length", max_length=77, return_tensors="pt")["input_ids"]
  with torch.no_grad():
    return (torch_features(reference_model.get_image_features(pixel_values=pixels)),
            torch_features(reference_model.get_text_features(input_ids=ids)))


# ----------------------------------------------------------------------------------------------
# Preprocessing.


@pytest.mark.parametrize("input_size, output_size", [
    ((64, 64), (224, 224)),  # Upsampling both ways.
    ((37, 91), (12, 96)),  # Shrinking height, growing width: vertical pass first.
    ((300, 227), (224, 224)),  # The height shrinks > 2x more pixels than the width: vertical first.
    ((300, 227), (120, 120)),  # Both shrink, horizontal first.
    ((500, 333), (224, 300)),
    ((13, 7), (4, 12)),
    ((80, 60), (80, 17)),  # One axis only.
])
def test_resize_is_bit_exact_with_pillow(input_size, output_size):
  shrink_height, shrink_width = (a - b for a, b in zip(input_size, output_size))
  if shrink_height > max(0, 2 * shrink_width) and int(PIL.__version__.split(".")[0]) < 13:
    pytest.skip("Pillow < 13 always resizes horizontally first")
  image = smooth_images(1, *input_size, seed=sum(input_size))[0]
  expected = np.asarray(PIL_Image.fromarray(image).resize(output_size[::-1],
                                                          PIL_Image.Resampling.BICUBIC))
  np.testing.assert_array_equal(clip_preprocessing.pil_bicubic_resize(image, *output_size),
                                expected)


@pytest.mark.slow
@pytest.mark.parametrize("height, width", [(224, 224), (480, 640), (300, 227), (50, 70)])
def test_preprocessing_matches_transformers_pil_backend(height, width):
  images = smooth_images(2, height, width, seed=height)
  expected = transformers.CLIPImageProcessorPil()(images=list(images),
                                                   return_tensors="np")["pixel_values"]
  ours = clip_preprocessing.CLIPPreprocessing()(images)
  np.testing.assert_allclose(ours, expected.transpose(0, 2, 3, 1), atol=1e-6, rtol=0)


def test_preprocessor_config_fields_are_read_and_unsupported_ones_refused(tmp_path):
  config = {"size": {"shortest_edge": 336}, "crop_size": 320, "image_mean": [0.5] * 3,
            "image_std": [0.25] * 3}
  preprocessing = clip_preprocessing.CLIPPreprocessing.from_dict(config)
  assert (preprocessing.shortest_edge, preprocessing.crop_height) == (336, 320)
  assert preprocessing.image_std == (0.25,) * 3
  with pytest.raises(InputError, match="resample"):
    clip_preprocessing.CLIPPreprocessing.from_dict({"resample": 2}, tmp_path / "config.json")


# ----------------------------------------------------------------------------------------------
# Towers and the directional similarity.


@pytest.mark.slow
@pytest.mark.parametrize("with_projection, hidden_act", [(True, "quick_gelu"), (False, "gelu")])
def test_vision_tower_matches_transformers(tmp_path, with_projection, hidden_act):
  torch.manual_seed(1)
  config = transformers.CLIPVisionConfig(**TINY_VISION, hidden_act=hidden_act, projection_dim=16)
  model_class = (transformers.CLIPVisionModelWithProjection if with_projection
                 else transformers.CLIPVisionModel)
  reference_model = perturbed(model_class(config), seed=1)
  reference_model.save_pretrained(tmp_path, safe_serialization=True)
  encoder = clip_vision.load_vision_encoder(tmp_path)
  assert encoder.config.with_projection == with_projection
  pixels = np.random.default_rng(2).normal(size=(3, IMAGE_SIZE, IMAGE_SIZE, 3)).astype(np.float32)
  with torch.no_grad():
    expected = reference_model(pixel_values=torch.from_numpy(pixels.transpose(0, 3, 1, 2)))
  output = encoder(pixels)
  np.testing.assert_allclose(output.last_hidden_state, expected.last_hidden_state.numpy(),
                             **TOLERANCE)
  if with_projection:
    np.testing.assert_allclose(output.image_embeds, expected.image_embeds.numpy(), **TOLERANCE)
  else:
    np.testing.assert_allclose(output.pooled_output, expected.pooler_output.numpy(), **TOLERANCE)
    assert output.image_embeds is None


def test_embeddings_and_directional_similarity_match_transformers(reference, model):
  reference_model, directory = reference
  original = smooth_images(3, 40, 52, seed=3)
  edited = original.copy()
  edited[:, 10:30, 15:40] = smooth_images(3, 20, 25, seed=4)
  image_original, text = reference_embeddings(reference_model, directory, original, CAPTIONS)
  image_edited, _ = reference_embeddings(reference_model, directory, edited, CAPTIONS)
  np.testing.assert_allclose(clip_similarity.image_embeddings(model, original), image_original,
                             **TOLERANCE)
  np.testing.assert_allclose(clip_similarity.text_embeddings(model, CAPTIONS), text, **TOLERANCE)
  unit = lambda x: torch.nn.functional.normalize(torch.from_numpy(x), dim=-1)
  expected = torch.nn.functional.cosine_similarity(
      unit(image_edited) - unit(image_original), unit(text[1:]) - unit(text[:1])).numpy()
  ours = clip_similarity.clip_directional_similarity(model, original, edited, *CAPTIONS)
  assert ours.shape == (3,)
  np.testing.assert_allclose(ours, expected, **TOLERANCE)
  # Swapping the captions reverses the text direction.
  np.testing.assert_allclose(
      clip_similarity.clip_directional_similarity(model, original, edited, *CAPTIONS[::-1]),
      -expected, **TOLERANCE)


def test_float_images_are_rounded_and_batches_do_not_recompile(model):
  images = smooth_images(5, 33, 47, seed=5)
  as_float = images.astype(np.float32) / 255 + 0.4 / 255  # Rounds back to the same levels.
  np.testing.assert_array_equal(clip_similarity.image_embeddings(model, as_float),
                                clip_similarity.image_embeddings(model, images))
  cache_size = clip_vision.encode._cache_size()  # pylint: disable=protected-access
  clip_similarity.image_embeddings(model, images[:3])  # A shorter last batch is padded.
  assert clip_vision.encode._cache_size() == cache_size  # pylint: disable=protected-access


def test_separate_tower_directories_load_the_same_model(reference, model, tmp_path):
  _, directory = reference
  tensors = load_file(directory / "model.safetensors")
  config = json.loads((directory / "config.json").read_text())
  for tower, prefix, projection, architecture in (
      ("vision", "vision_model.", "visual_projection.weight", "CLIPVisionModelWithProjection"),
      ("text", "text_model.", "text_projection.weight", "CLIPTextModelWithProjection")):
    (tmp_path / tower).mkdir()
    save_file({name: value for name, value in tensors.items()
               if name.startswith(prefix) or name == projection},
              str(tmp_path / tower / "model.safetensors"))
    tower_config = dict(config[f"{tower}_config"], projection_dim=config["projection_dim"],
                        architectures=[architecture])
    (tmp_path / tower / "config.json").write_text(json.dumps(tower_config))
  write_tokenizer_and_processor(tmp_path / "text")
  (tmp_path / "vision" / "preprocessor_config.json").write_text(json.dumps(PREPROCESSOR))
  separate = clip_similarity.load_clip_model(vision_directory=tmp_path / "vision",
                                             text_directory=tmp_path / "text", batch_size=4)
  images = smooth_images(2, 36, 36, seed=6)
  np.testing.assert_array_equal(clip_similarity.image_embeddings(separate, images),
                                clip_similarity.image_embeddings(model, images))
  np.testing.assert_array_equal(clip_similarity.text_embeddings(separate, CAPTIONS),
                                clip_similarity.text_embeddings(model, CAPTIONS))


def test_checkpoint_errors_name_the_problem(reference, tmp_path):
  _, directory = reference
  tensors = load_file(directory / "model.safetensors")
  del tensors["vision_model.encoder.layers.1.mlp.fc2.bias"]
  save_file(tensors, str(tmp_path / "model.safetensors"))
  for name in ("config.json", "vocab.json", "merges.txt"):
    (tmp_path / name).write_text((directory / name).read_text("utf-8"), "utf-8")
  (tmp_path / "preprocessor_config.json").write_text(json.dumps(PREPROCESSOR))
  with pytest.raises(InputError, match=r"missing tensor vision_model\.encoder\.layers\.1\.mlp"):
    clip_similarity.load_clip_model(tmp_path)
  (tmp_path / "model.safetensors").unlink()
  (tmp_path / "model.safetensors").symlink_to(directory / "model.safetensors")
  (tmp_path / "preprocessor_config.json").write_text(json.dumps({"crop_size": 224}))
  with pytest.raises(InputError, match="crops 224x224 but the vision tower takes 32x32"):
    clip_similarity.load_clip_model(tmp_path)
  with pytest.raises(ValueError, match="either a CLIPModel directory"):
    clip_similarity.load_clip_model(tmp_path, vision_directory=tmp_path)
