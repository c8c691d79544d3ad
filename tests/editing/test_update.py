"""The image set update: resumable with nothing lost, one compilation, sharding-invariant."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import files
from signerf_jax.diffusion import sampler
from signerf_jax.editing import generation
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing import update
from signerf_jax.errors import InputError

from random_pipeline import TINY_OPTIONS

TILE = 16
LAYOUT = sheet_lib.SheetLayout(tile_height=TILE, tile_width=TILE)
NUM_VIEWS, VIEW_SIZE = 7, 24


def make_views(count=NUM_VIEWS, seed=0, size=VIEW_SIZE) -> update.SlotViews:
  """Random views with a disc mask each (empty for none: the caller chooses the indices)."""
  rng = np.random.default_rng(seed)
  rows, columns = np.mgrid[:size, :size] + 0.5
  centres = rng.uniform(0.3 * size, 0.7 * size, (count, 2))
  distance = np.hypot(rows[None] - centres[:, :1, None], columns[None] - centres[:, 1:, None])
  masks = np.clip((0.25 * size - distance) / 2.0, 0.0, 1.0).astype(np.float32)
  boxes = np.asarray([[0.0, 0.0, size, size]] * count, np.float32)
  return update.SlotViews(images=rng.uniform(0, 1, (count, size, size, 3)).astype(np.float32),
                          masks=masks, controls=rng.uniform(0, 1, (count, size, size)
                                                            ).astype(np.float32), boxes=boxes)


def make_sheet(seed=1):
  rng = np.random.default_rng(seed)
  height, width = LAYOUT.sheet_shape
  return (rng.uniform(0, 1, (height, width, 3)).astype(np.float32),
          rng.uniform(0, 1, (height, width, 1)).astype(np.float32))


@pytest.fixture(scope="module")
def generator(random_model):
  return generation.load_generator(str(random_model), "", "", "a red cow", "", TINY_OPTIONS,
                                   views_per_device=4)


def take(views, indices) -> update.SlotViews:
  return update.SlotViews(*(array[indices] for array in (
      views.images, views.masks, views.controls, views.boxes)))


def run(generator, directory, views, propagation="sheet", **options):
  edit_batch = update.batch_editor(generator, LAYOUT, propagation, *make_sheet())
  return update.run_update(generator, edit_batch, np.arange(len(views.images)),
                           lambda indices: take(views, indices), directory, seed=5,
                           progress=False, **options)


def written(directory):
  return {path.relative_to(directory).as_posix(): path.read_bytes()
          for path in sorted(Path(directory).rglob("*.png"))}


@pytest.mark.slow
def test_an_interrupted_update_resumes_to_exactly_the_uninterrupted_images(generator, tmp_path):
  views = make_views()
  complete = run(generator, tmp_path / "complete", views)
  assert complete == {"edited": NUM_VIEWS, "resumed": 0, "batches": 2, "batch_size": 4,
                      "devices": 1}

  def interrupt_after_three(view_index):
    if len(list((tmp_path / "resumed" / "images").glob("*.png"))) == 3:
      raise KeyboardInterrupt  # What Ctrl-C raises, between two views of a batch.

  program = sampler.program(generator.pipeline.models)
  cache_size = program._cache_size()  # pylint: disable=protected-access
  with pytest.raises(KeyboardInterrupt):
    run(generator, tmp_path / "resumed", views, on_view_written=interrupt_after_three)
  assert len(written(tmp_path / "resumed")) == 2 * 3  # Three views: tile and image each.
  resumed = run(generator, tmp_path / "resumed", views)
  assert resumed["resumed"] == 3 and resumed["edited"] == NUM_VIEWS - 3
  assert written(tmp_path / "resumed") == written(tmp_path / "complete")
  # Every batch has the same shape: nothing compiled after the first run.
  assert program._cache_size() == cache_size  # pylint: disable=protected-access
  # A finished update does no work at all.
  assert run(generator, tmp_path / "resumed", views)["batches"] == 0


def test_sheets_are_handed_over_batch_by_batch_as_they_are_made(generator):
  """What lets the preview show its first candidates while the others are generated."""
  rgb, control = make_sheet()
  inputs = generation.SheetInputs(rgb, control, (control > 0.5).astype(np.float32), LAYOUT)
  recipes = [generation.SheetRecipe.parse(text) for text in ("0", "1", "2", "3", "4", "2/1@9")]
  batches = []
  sheets = generation.generate_sheets(generator, inputs, recipes, on_batch=batches.append)
  assert [[str(recipe) for recipe in batch] for batch in batches] == [
      ["0", "1", "2", "3"], ["4"], ["2/1@9"]]  # Batches of generator.batch_size = 4.
  for batch in batches:
    for recipe, sheet in batch.items():
      np.testing.assert_array_equal(sheet, sheets[recipe])


def test_the_update_changes_only_masked_pixels_and_only_the_slot(generator):
  views = make_views(3)
  sheet_rgb, sheet_control = make_sheet()
  keys = np.stack([generation.view_key(0, index) for index in range(3)])
  edited, slots = update.update_batch(generator, sheet_rgb, sheet_control, LAYOUT, views, keys)
  assert edited.shape == views.images.shape and slots.shape == (3, TILE, TILE, 3)
  outside = views.masks == 0
  np.testing.assert_array_equal(edited[outside], views.images[outside])
  assert np.abs(edited - views.images)[views.masks == 1].mean() > 0.01
  # A view's result depends on its own key only, not on its batch (every batch is padded to
  # the generator's batch size: one program, the same rounding).
  alone, _ = update.update_batch(generator, sheet_rgb, sheet_control, LAYOUT,
                                 take(views, slice(1, 2)), keys[1:2])
  np.testing.assert_array_equal(alone[0], edited[1])


@pytest.mark.slow
def test_independent_propagation_edits_each_view_without_the_sheet(generator, tmp_path):
  views = make_views(5)
  report = run(generator, tmp_path / "independent", views, propagation="independent")
  assert report["edited"] == 5 and report["batches"] == 2
  images = np.stack([np.asarray(files.read_image(
      update.edited_image_path(tmp_path / "independent", index)))[..., :3] for index in range(5)])
  outside = views.masks == 0
  np.testing.assert_allclose(images[outside], views.images[outside], atol=1 / 255)
  # The same views through the sheet differ: the sheet conditions them.
  run(generator, tmp_path / "sheet", views)
  through_sheet = np.stack([np.asarray(files.read_image(
      update.edited_image_path(tmp_path / "sheet", index)))[..., :3] for index in range(5)])
  assert np.abs(through_sheet - images)[views.masks == 1].mean() > 0.01
  # A view's independent edit is its own: the same alone as in a batch.
  keys = np.stack([generation.view_key(5, index) for index in range(5)])
  alone, tiles = update.independent_batch(generator, LAYOUT, take(views, slice(3, 4)), keys[3:4])
  assert tiles.shape == (1, TILE, TILE, 3)
  np.testing.assert_allclose(alone[0], images[3], atol=1 / 255 + 1e-5)


def test_an_unknown_propagation_is_refused(generator):
  with pytest.raises(InputError, match="UpdateConfig.propagation"):
    update.batch_editor(generator, LAYOUT, "telepathy")


def test_crops_cut_tiles_around_the_selection_and_paste_back_through_the_mask(generator):
  views = make_views(2, size=48)
  views = update.SlotViews(views.images, views.masks, views.controls,
                           np.asarray([[8.0, 8.0, 24.0, 24.0], [12.0, 4.0, 24.0, 24.0]],
                                      np.float32))
  sheet_rgb, sheet_control = make_sheet()
  keys = np.stack([generation.view_key(0, index) for index in range(2)])
  edited, _ = update.update_batch(generator, sheet_rgb, sheet_control, LAYOUT, views, keys)
  outside = views.masks == 0
  np.testing.assert_array_equal(edited[outside], views.images[outside])


# Runs in a process with eight CPU devices: the same eight views sharded over 2, 4 and 8 of them.
SHARDED_DEVICE_COUNTS = (2, 4, 8)
SHARDED_VIEWS = 8
SHARDED_UPDATE = textwrap.dedent("""
    import sys
    import jax
    import numpy as np
    model, tests, output = sys.argv[1:]
    sys.path.insert(0, tests)
    from signerf_jax import parallel
    from signerf_jax.editing import generation, update
    from random_pipeline import TINY_OPTIONS
    from test_update import LAYOUT, SHARDED_DEVICE_COUNTS, SHARDED_VIEWS, make_sheet, make_views
    assert len(jax.devices()) == max(SHARDED_DEVICE_COUNTS)
    views = make_views(SHARDED_VIEWS)
    keys = np.stack([generation.view_key(3, index) for index in range(SHARDED_VIEWS)])
    results = {}
    for count in SHARDED_DEVICE_COUNTS:
      mesh = parallel.device_mesh(jax.devices()[:count], generation.MESH_AXIS)
      generator = generation.load_generator(model, "", "", "a red cow", "", TINY_OPTIONS,
                                            views_per_device=SHARDED_VIEWS // count, mesh=mesh)
      results[f"shards_{count}"] = len(generator.shard(views.images).sharding.device_set)
      results[f"edited_{count}"] = update.update_batch(generator, *make_sheet(), LAYOUT, views,
                                                       keys)[0]
    np.savez(output, **results)
""")


@pytest.mark.slow
def test_the_update_sharded_over_two_four_and_eight_devices_equals_the_one_device_update(
    generator, random_model, tmp_path):
  output = tmp_path / "sharded.npz"
  environment = dict(os.environ, JAX_PLATFORMS="cpu",
                     JAX_NUM_CPU_DEVICES=str(max(SHARDED_DEVICE_COUNTS)))
  result = subprocess.run([sys.executable, "-c", SHARDED_UPDATE, str(random_model),
                           str(Path(__file__).parent), str(output)], env=environment,
                          capture_output=True, text=True, timeout=600, check=False)
  assert result.returncode == 0, result.stderr[-3000:]
  sharded = np.load(output)
  # Here: one device, the same views in batches of four.
  assert len(generator.mesh.devices.ravel()) == 1 and generator.batch_size == 4
  views = make_views(SHARDED_VIEWS)
  keys = np.stack([generation.view_key(3, index) for index in range(SHARDED_VIEWS)])
  edited = np.concatenate([
      update.update_batch(generator, *make_sheet(), LAYOUT, take(views, batch), keys[batch])[0]
      for batch in np.split(np.arange(SHARDED_VIEWS), SHARDED_VIEWS // 4)])
  for count in SHARDED_DEVICE_COUNTS:
    assert int(sharded[f"shards_{count}"]) == count
    np.testing.assert_allclose(sharded[f"edited_{count}"], edited, rtol=0, atol=1e-5,
                               err_msg=f"{count} devices")


@pytest.mark.slow
def test_a_bfloat16_generator_stores_bfloat16_weights_and_edits_views_alike(
    generator, random_model, monkeypatch, tmp_path):
  """EditConfig.diffusion_precision = "bfloat16": the weights are stored in bfloat16 and the
  update's images stay within bfloat16's rounding of the float32 ones; on a CPU without bf16
  instructions (a Zen 3's flags) loading warns that it is slower there."""
  (tmp_path / "cpuinfo").write_text("processor : 0\nflags : fpu sse2 avx avx2 fma\n")
  monkeypatch.setattr(generation, "CPUINFO", tmp_path / "cpuinfo")
  with pytest.warns(UserWarning, match="without bf16 instructions"):
    reduced = generation.load_generator(str(random_model), "", "", "a red cow", "",
                                        TINY_OPTIONS, views_per_device=4, precision="bfloat16")
  dtypes = lambda g: {leaf.dtype for leaf in jax.tree.leaves(g.pipeline.models.unet_params)}
  assert dtypes(reduced) == {np.dtype(jnp.bfloat16)}
  assert dtypes(generator) == {np.dtype(np.float32)}
  views = make_views(count=2)
  edit = lambda g: update.batch_editor(g, LAYOUT, "sheet", *make_sheet())(
      take(views, [0, 1]), np.stack([generation.seed_key(seed) for seed in (0, 1)]))[0]
  full, half = np.asarray(edit(generator)), np.asarray(edit(reduced))
  assert np.all(np.isfinite(half))
  assert 0 < np.mean(np.abs(full - half)) < 0.02


@pytest.mark.parametrize("flags, lacks", [("fpu avx2 fma", True),
                                          ("fpu avx512f avx512_bf16", False),
                                          ("fp asimd bf16 i8mm", False), (None, False)])
def test_bf16_instructions_are_read_from_the_cpu_flags(monkeypatch, tmp_path, flags, lacks):
  cpuinfo = tmp_path / "cpuinfo"  # None: no such file, nothing to tell.
  if flags is not None:
    cpuinfo.write_text(f"processor : 0\nflags : {flags}\n")
  monkeypatch.setattr(generation, "CPUINFO", cpuinfo)
  assert generation.cpu_lacks_bf16_instructions() is lacks
