"""The on-disk dataset: shards, manifest, resuming, held-out split, batches and model inputs."""

import dataclasses
import json

import numpy as np
import pytest

from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.default_model import batches, captions, dataset_builder
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.errors import InputError
from signerf_jax.metrics import colors


def tiny_settings(directory, **changes) -> dataset_builder.DataSettings:
  return dataclasses.replace(dataset_builder.DataSettings(
      output_directory=str(directory), num_sheets=3, num_singles=5, num_eval_sheets=2,
      num_eval_singles=8, sheets_per_shard=2, singles_per_shard=2), **changes)


@pytest.fixture(scope="module")
def built(tmp_path_factory, tiny_sampling):
  directory = tmp_path_factory.mktemp("data")
  manifest = dataset_builder.build_dataset(tiny_settings(directory), tiny_sampling, progress=False)
  return directory, manifest


def test_manifest_counts_and_shard_arrays(built, tiny_sampling):
  directory, manifest = built
  assert manifest["complete"] and dataset_builder.read_manifest(directory) == json.loads(
      json.dumps(manifest))
  counts = {(split, kind): manifest["splits"][split][kind]["samples"]
            for split in dataset_builder.SPLITS for kind in dataset_builder.KINDS}
  assert counts == {("train", "sheets"): 3, ("train", "singles"): 5, ("eval", "sheets"): 2,
                    ("eval", "singles"): 8}
  paths = dataset_builder.shard_paths(directory, "train", "sheets")
  assert [path.name for path in paths] == ["shard_00000.npz", "shard_00001.npz"]
  shard = dataset_builder.read_shard(paths[1])
  size, views = tiny_sampling.image_size, tiny_sampling.sheet_tiles + 1
  assert shard["rgb"].shape == (1, views, size, size, 3) and shard["rgb"].dtype == np.uint8
  assert shard["depth"].dtype == np.float16
  assert shard["dilated_silhouettes"].shape == (1, views, 3, size, size)
  assert list(shard["sample_index"]) == [2]
  assert json.loads(str(shard["shard_info"]))["fingerprint"] == manifest["fingerprint"]
  for caption, kind, color, pattern, names_color, names_pattern in zip(
      shard["caption"], shard["kind"], shard["color"], shard["pattern"], shard["names_color"],
      shard["names_pattern"]):
    assert captions.parse_caption(str(caption)) == captions.Attributes(
        str(kind), str(color) if names_color else None, str(pattern) if names_pattern else None)


def test_tokenizer_is_saved_and_covers_every_caption(built):
  directory, _ = built
  tokenizer = tokenizer_lib.load_tokenizer(directory / dataset_builder.TOKENIZER_FOLDER)
  texts = [str(text) for kind in dataset_builder.KINDS
           for path in dataset_builder.shard_paths(directory, "train", kind)
           for text in dataset_builder.read_shard(path)["caption"]]
  assert tokenizer.unk_id not in tokenizer.tokenize(texts)


def test_eval_split_is_balanced_and_held_out(built, tiny_sampling):
  directory, _ = built
  [path] = dataset_builder.shard_paths(directory, "eval", "singles")[:1]
  shard = dataset_builder.read_shard(path)
  assert list(shard["color"]) == list(colors.COLORS[:2])
  kinds = [kind.name for kind in tiny_sampling.catalogue()]
  assert list(shard["kind"]) == kinds[:2]
  train = dataset_builder.read_shard(dataset_builder.shard_paths(directory, "train", "singles")[0])
  assert not np.array_equal(train["rgb"][0], shard["rgb"][0])


def test_samples_do_not_depend_on_shard_size_and_resuming_skips_finished_shards(
    built, tmp_path, tiny_sampling):
  directory, _ = built
  other = tiny_settings(tmp_path, sheets_per_shard=3, singles_per_shard=5, num_eval_sheets=0,
                        num_eval_singles=0)
  dataset_builder.build_dataset(other, tiny_sampling, progress=False)
  for kind in dataset_builder.KINDS:
    def by_index(root):
      shards = [dataset_builder.read_shard(path)
                for path in dataset_builder.shard_paths(root, "train", kind)]
      return np.concatenate([shard["rgb"] for shard in shards])
    np.testing.assert_array_equal(by_index(directory), by_index(tmp_path))
  # Remove one shard: a re-run makes exactly that one again, with the same content.
  paths = dataset_builder.shard_paths(tmp_path, "train", "singles")
  before = dataset_builder.read_shard(paths[0])
  sheets = dataset_builder.shard_paths(tmp_path, "train", "sheets")[0]
  sheets_time = sheets.stat().st_mtime_ns
  paths[0].unlink()
  manifest = dataset_builder.build_dataset(other, tiny_sampling, progress=False)
  assert manifest["complete"] and sheets.stat().st_mtime_ns == sheets_time
  after = dataset_builder.read_shard(paths[0])
  for name in before:
    np.testing.assert_array_equal(before[name], after[name], err_msg=name)
  # Other settings in the same directory are refused rather than mixed in.
  with pytest.raises(InputError, match="other settings"):
    dataset_builder.build_dataset(dataclasses.replace(other, seed=7), tiny_sampling,
                                  progress=False)


def test_batches_cover_each_sample_once_per_epoch_deterministically(built):
  directory, _ = built
  run = lambda seed: [batch["sample_index"].tolist() for batch in dataset_builder.iterate_batches(
      directory, "eval", "singles", batch_size=3, seed=seed, epochs=2)]
  first = run(0)
  assert first == run(0) and first != run(1)
  assert len(first) == 4  # 8 samples: 2 full batches of 3 per epoch, the rest dropped.
  for epoch in (first[:2], first[2:]):
    indices = sum(epoch, [])
    assert len(set(indices)) == 6 and set(indices) <= set(range(8))


def test_single_view_inputs_hide_the_object(built, tiny_sampling):
  directory, manifest = built
  arrays = next(dataset_builder.iterate_batches(directory, "eval", "singles", 8, seed=0))
  kinds = batches.mask_kinds(manifest["dilation_radii"])
  assert kinds == ("silhouette", "dilated_2", "dilated_4", "dilated_8", "box")
  candidates = batches.candidate_masks(arrays)
  for coarser in range(1, len(kinds)):  # Every kind covers the silhouette; dilations nest.
    assert np.all(candidates[:, :, coarser] >= candidates[:, :, 0])
  assert np.all(candidates[:, :, 3] >= candidates[:, :, 2])
  chosen = np.arange(8) % len(kinds)
  masks = batches.inpainting_masks(arrays, chosen)
  np.testing.assert_array_equal(masks, candidates[np.arange(8), :, chosen])
  inputs = batches.single_view_inputs(arrays, masks)
  size = tiny_sampling.image_size
  assert inputs["image"].shape == (8, size, size, 3) and inputs["control"].shape == (8, size, size, 1)
  background = arrays["background_rgb"][:, 0] / 255.0
  np.testing.assert_allclose(inputs["masked_image"], background * (1 - masks[:, 0, ..., None]),
                             atol=1e-6)
  control = np.asarray(inputs["control"])[..., 0]
  silhouette = arrays["silhouette"][:, 0] > 0
  np.testing.assert_array_equal(np.asarray(inputs["object"])[..., 0], silhouette)
  assert control.min() >= 0 and control.max() <= 1
  assert np.all((control[silhouette] > 0) & (control[silhouette] < 1))


def test_sheet_inputs_for_each_mode(built, tiny_sampling):
  directory, manifest = built
  arrays = next(dataset_builder.iterate_batches(directory, "train", "sheets", 2, seed=0))
  size = tiny_sampling.image_size
  layout = sheet_lib.SheetLayout(tile_height=size, tile_width=size)
  masks = batches.inpainting_masks(arrays, np.array([4, 3]))
  tile = lambda sheet, row, column: np.asarray(sheet)[:, row * size:(row + 1) * size,
                                                     column * size:(column + 1) * size]
  views = arrays["rgb"] / 255.0
  everything = batches.sheet_inputs(arrays, masks, layout, "all_views")
  assert everything["image"].shape == (2, 2 * size, 3 * size, 3)
  np.testing.assert_allclose(tile(everything["image"], 0, 1), views[:, 1], atol=1e-6)
  np.testing.assert_allclose(tile(everything["image"], 1, 2), views[:, 5], atol=1e-6)
  np.testing.assert_array_equal(tile(everything["mask"], 1, 2)[..., 0], masks[:, 5])
  silhouettes = arrays["silhouette"] > 0

  reference = batches.sheet_inputs(arrays, masks, layout, "reference_sheet")
  np.testing.assert_allclose(tile(reference["image"], 1, 2), sheet_lib.EMPTY_SLOT_COLOR)
  assert not np.any(tile(reference["mask"], 1, 2)) and not np.any(tile(reference["control"], 1, 2))
  np.testing.assert_array_equal(tile(reference["mask"], 0, 0)[..., 0], masks[:, 0])
  for inputs in (everything, reference):  # Every view's silhouette, in every mode.
    np.testing.assert_array_equal(tile(inputs["object"], 0, 1)[..., 0], silhouettes[:, 1])
    np.testing.assert_array_equal(tile(inputs["object"], 1, 2)[..., 0], silhouettes[:, 5])

  update = batches.sheet_inputs(arrays, masks, layout, "slot_update")
  np.testing.assert_array_equal(tile(update["mask"], 1, 2)[..., 0], masks[:, 5])
  mask_sheet = np.asarray(update["mask"]).copy()
  mask_sheet[:, size:, 2 * size:] = 0
  assert not mask_sheet.any()  # Only the slot is inpainted.
  np.testing.assert_allclose(update["masked_image"], np.asarray(update["image"]) * (
      1 - np.asarray(update["mask"])), atol=1e-6)
  with pytest.raises(InputError, match="layout"):
    batches.sheet_inputs(arrays, masks, sheet_lib.SheetLayout(tile_height=64, tile_width=64))
