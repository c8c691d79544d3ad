"""The default model's quality-gate metrics, on constructed arrays with known answers."""

import types

import numpy as np
import pytest

from signerf_jax.default_model import (batches, captions, evaluation, evaluation_generation,
                                       evaluation_singles, generated_objects, samples)
from signerf_jax.errors import InputError
from signerf_jax.metrics import silhouettes

RED, BLUE, GREEN = (0.8, 0.1, 0.08), (0.12, 0.25, 0.85), (0.15, 0.65, 0.18)


def striped_ground(size=24):
  """[size, size, 3] a grey striped background (a texture the segmentation must ignore)."""
  stripes = 0.35 + 0.3 * (np.arange(size) // 3 % 2)
  return np.repeat(np.broadcast_to(stripes[None, :, None], (size, size, 1)), 3, -1).astype(
      np.float32)


def scene_with_object():
  """(generated, background, mask, the object's true silhouette) for one 24-pixel view.

  A red 8 x 8 object with a background-coloured pinhole, a one-pixel speck and a small
  change just below the threshold inside the mask, and a large change outside it."""
  background = striped_ground()
  generated = background.copy()
  silhouette = np.zeros((24, 24), bool)
  silhouette[6:14, 8:16] = True
  generated[silhouette] = RED
  generated[9, 11] = background[9, 11]  # A pinhole: the object matches the ground there.
  generated[19, 4] += 0.5  # A speck of regenerated texture.
  generated[2:5, 2:5] += 0.08  # Below the threshold.
  generated[0:4, 20:24] = BLUE  # Outside the mask.
  mask = np.zeros((24, 24), np.float32)
  mask[1:22, 1:19] = 1.0
  return generated, background, mask, silhouette


def test_segmentation_finds_the_object_and_ignores_specks_and_the_unmasked():
  generated, background, mask, silhouette = scene_with_object()
  found = generated_objects.segment_objects(generated[None], background[None], mask[None],
                                            difference_threshold=0.1, min_component_pixels=4)
  np.testing.assert_array_equal(found[0], silhouette)


def test_segmentation_without_clean_up_keeps_the_speck_and_the_hole():
  generated, background, mask, silhouette = scene_with_object()
  found = generated_objects.segment_objects(generated[None], background[None], mask[None],
                                            difference_threshold=0.1, min_component_pixels=1)[0]
  assert found[19, 4] and not found[9, 11]
  assert found.sum() == silhouette.sum()  # One pixel missing (the hole), one extra (the speck).


@pytest.mark.parametrize("threshold, expected", [(0.05, True), (0.2, False)])
def test_segmentation_threshold_is_per_channel(threshold, expected):
  background = np.full((1, 8, 8, 3), 0.5, np.float32)
  generated = background.copy()
  generated[0, 2:6, 2:6, 1] += 0.1  # One channel moves by 0.1.
  found = generated_objects.segment_objects(generated, background, np.ones((1, 8, 8)), threshold,
                                            4)
  assert found[0, 3, 3] == expected


def test_hue_segmentation_finds_the_named_colour_and_ignores_repainted_ground():
  generated, _, mask, silhouette = scene_with_object()
  generated[9, 11] = RED  # No pinhole: hue segmentation does not look at the ground.
  generated[1:22, 16:19] = striped_ground()[1:22, 16:19] + 0.2  # Ground repainted lighter.
  found = generated_objects.segment_by_hue(generated[None], mask[None], ["red"],
                                           min_component_pixels=4)
  np.testing.assert_array_equal(found[0], silhouette)
  assert not generated_objects.segment_by_hue(generated[None], mask[None], ["blue"], 4).any()
  # The difference segmentation counts the repainted ground as object.
  by_difference = generated_objects.segment_objects(generated[None], striped_ground()[None],
                                                    mask[None], 0.1, 4)
  assert by_difference[0, 5, 17] and not found[0, 5, 17]


def test_hue_shape_adherence_looks_only_inside_the_masks_the_views_were_inpainted_under():
  generated, _, box, silhouette = scene_with_object()
  generated[9, 11] = RED
  generated[15:20, 8:16] = RED  # A red blob in the box but off the object.
  proxy = np.zeros_like(box)
  proxy[5:15, 7:17] = 1.0  # The silhouette dilated by one pixel.
  views = types.SimpleNamespace(captions=["a red cow", "a cow"],
                                silhouettes=silhouette[None].repeat(2, 0),
                                truth_round_trip=generated[None].repeat(2, 0))
  settings = evaluation.EvaluationSettings()
  generations = [generated[None].repeat(2, 0)]
  with_proxy = evaluation_singles._by_caption_hue(generations, views, proxy[None].repeat(2, 0),
                                                  settings)
  with_box = evaluation_singles._by_caption_hue(generations, views, box[None].repeat(2, 0),
                                                settings)
  assert with_proxy["samples"] == 1  # The caption without a colour is left out.
  assert with_proxy["mean_iou"] == [pytest.approx(1.0)]
  assert with_box["mean_iou"] == [pytest.approx(64 / (64 + 40))]


def test_precision_recall_and_changed_ground_say_where_the_iou_is_lost():
  generated, _, mask, silhouette = scene_with_object()
  generated[1:22, 16:19] = striped_ground()[1:22, 16:19] + 0.2  # Ground repainted lighter.
  found = generated_objects.segment_objects(generated[None], striped_ground()[None], mask[None],
                                            0.1, 4)
  precision, recall = silhouettes.pooled_precision_recall(found, silhouette[None])
  hits = np.sum(found & silhouette)
  assert precision == pytest.approx(hits / found.sum()) and precision < 1
  assert recall == pytest.approx(hits / silhouette.sum())
  ground = (mask >= 0.5) & ~silhouette
  repainted = ground.copy()
  repainted[:, :16] = repainted[:, 19:] = False
  repainted[:1] = repainted[22:] = False
  repainted[19, 4] = True  # The speck: counted before specks are dropped.
  share = generated_objects.changed_ground_share(generated[None], striped_ground()[None],
                                                 mask[None], silhouette[None], 0.1)
  assert share == pytest.approx(repainted.sum() / ground.sum())
  assert generated_objects.changed_ground_share(striped_ground()[None], striped_ground()[None],
                                                mask[None], silhouette[None], 0.1) == 0.0
  assert np.isnan(silhouettes.pooled_precision_recall(np.zeros((1, 4, 4), bool),
                                                     np.ones((1, 4, 4), bool))[0])


def test_segmentation_recovers_rendered_objects(tiny_sampling):
  """On true renders (a perfect generator) the IoU with the silhouette is near 1."""
  ious = []
  for seed in range(4):
    views = samples.make_sample(np.random.default_rng(seed), tiny_sampling,
                                captions.CaptionSettings(), sheet=False).views
    rgb, background = (views[name].astype(np.float32) / 255 for name in ("rgb", "background_rgb"))
    mask = batches.box_masks(views["boxes"], tiny_sampling.image_size, tiny_sampling.image_size)
    found = generated_objects.segment_objects(rgb, background, mask, 0.1, 4)
    ious.append(silhouettes.silhouette_iou(found, views["silhouette"] > 0)[0])
  assert np.mean(ious) > 0.9, ious


def test_object_colors_names_and_means():
  images = np.zeros((3, 8, 8, 3), np.float32)
  images[0, 2:6, 2:6] = RED
  images[1, 2:6, 2:6] = BLUE
  objects = np.zeros((3, 8, 8), bool)
  objects[:2, 2:6, 2:6] = True
  names, means = generated_objects.object_colors(images, objects)
  assert names == ["red", "blue", None]
  np.testing.assert_allclose(means[:2], [RED, BLUE], atol=1e-6)
  assert np.all(np.isnan(means[2]))


def test_color_agreement_counts_pairs():
  assert generated_objects.color_agreement(["red", "red", "blue"]) == pytest.approx(1 / 3)
  assert generated_objects.color_agreement(["green"] * 5) == 1.0
  # Missing objects agree with nothing.
  assert generated_objects.color_agreement([None, None]) == 0.0
  assert generated_objects.color_agreement(["red"], ["red", "blue", "red", "red"]) == 0.75
  with pytest.raises(InputError):
    generated_objects.color_agreement(["red"])


def test_mean_color_distance_skips_missing_objects():
  means = np.array([[0.0, 0.0, 0.0], [0.0, 0.3, 0.4], [np.nan] * 3])
  assert generated_objects.mean_color_distance(means) == pytest.approx(0.5)
  assert generated_objects.mean_color_distance(means[:1], means) == pytest.approx(0.25)
  assert np.isnan(generated_objects.mean_color_distance(means[2:], means[:1]))


@pytest.mark.parametrize("ious, rising, shape_passes", [
    ([0.3, 0.5, 0.7, 0.8, 0.85], True, True),
    ([0.3, 0.5, 0.7, 0.86, 0.85], True, True),  # Within the tolerance.
    ([0.3, 0.5, 0.9, 0.8, 0.85], False, False),
    ([0.85] * 5, False, False),  # The scale changes nothing.
    ([0.3, 0.5, 0.6, 0.7, 0.75], True, False),
])
def test_quality_gates_shape(ious, rising, shape_passes):
  gates = evaluation.quality_gates(0.95, ious, (0.0, 0.25, 0.5, 0.75, 1.0),
                                   {"sheet": 0.9, "slot_update": 0.8, "independent": 0.2},
                                   evaluation.QualityGates())
  assert gates["shape_adherence"]["rising"] == rising
  assert gates["shape_adherence"]["passed"] == shape_passes
  assert gates["shape_adherence"]["iou_at_full_scale"] == ious[-1]
  assert gates["prompt_adherence"]["passed"] and gates["consistency"]["passed"]


@pytest.mark.parametrize("color, agreement, color_passes, consistency_passes", [
    (0.89, {"sheet": 0.9, "slot_update": 0.8, "independent": 0.2}, False, True),
    (0.9, {"sheet": 0.9, "slot_update": 0.45, "independent": 0.2}, True, False),
    (1.0, {"sheet": 0.4, "slot_update": 0.9, "independent": 0.2}, True, False),
])
def test_quality_gates_color_and_consistency(color, agreement, color_passes, consistency_passes):
  gates = evaluation.quality_gates(color, [0.3, 0.9], (0.0, 1.0), agreement,
                                   evaluation.QualityGates())
  assert gates["prompt_adherence"]["passed"] == color_passes
  assert gates["consistency"]["passed"] == consistency_passes
  assert gates["consistency"]["margins_over_independent"]["slot_update"] == pytest.approx(
      agreement["slot_update"] - agreement["independent"])


def test_evaluation_keys_are_reproducible_and_distinct():
  key = evaluation_generation.evaluation_key(0, "sheet", 3, 1)
  np.testing.assert_array_equal(key, evaluation_generation.evaluation_key(0, "sheet", 3, 1))
  assert key.shape == (2,) and key.dtype == np.uint32
  others = [evaluation_generation.evaluation_key(*arguments) for arguments in
            ((1, "sheet", 3, 1), (0, "slot", 3, 1), (0, "sheet", 4, 1), (0, "sheet", 3, 2))]
  assert len({tuple(key)} | {tuple(other) for other in others}) == 5


def test_call_timer_separates_compilation(monkeypatch):
  clock = iter([0.0, 10.0, 20.0, 22.0, 30.0, 32.5, 40.0, 41.0, 50.0, 56.0])
  monkeypatch.setattr(evaluation_generation, "time",
                      types.SimpleNamespace(perf_counter=lambda: next(clock)))
  timer = evaluation_generation.CallTimer()
  shape = (64, 64, 3)
  for task, input_shape in (("single", shape), ("single", shape), ("single", shape),
                            ("slot", (128, 192, 3)), ("other_slot", (128, 192, 3))):
    timer.time(task, input_shape, 4, lambda: None)
  summary = timer.summary()
  # Calls of 10, 2, 2.5 s: the first compiled.
  assert summary["single"]["first_call_seconds"] == 10.0
  assert summary["single"]["steady_call_seconds"] == pytest.approx(2.25)
  assert summary["single"]["compile_seconds"] == pytest.approx(7.75)
  assert summary["single"]["seconds_per_sample"] == pytest.approx(2.25 / 4)
  # A new shape compiles again; a task reusing it does not.
  assert summary["slot"]["steady_call_seconds"] is None
  assert summary["slot"]["compile_seconds"] is None
  assert summary["other_slot"]["steady_call_seconds"] == 6.0
  assert "first_call_seconds" not in summary["other_slot"]


def test_settings_need_ascending_scales_with_full_scale():
  with pytest.raises(InputError) as error:
    evaluation.EvaluationSettings(controlnet_scales=(0.0, 0.5))
  assert error.value.field == "default_model_evaluation.controlnet_scales"
  with pytest.raises(InputError):
    evaluation.EvaluationSettings(controlnet_scales=(1.0, 0.5))


def test_select_samples_takes_sheets_without_a_color():
  singles = {"caption": np.array(["a cow"] * 5)}
  sheets = {"names_color": np.array([True, False, True, False, False])}
  settings = evaluation.EvaluationSettings(num_singles=3, num_sheets=2)
  single_indices, sheet_indices = evaluation_generation.select_samples(singles, sheets, settings)
  np.testing.assert_array_equal(single_indices, [0, 1, 2])
  np.testing.assert_array_equal(sheet_indices, [1, 3])
  with pytest.raises(InputError) as error:
    evaluation_generation.select_samples(singles, sheets,
                                         evaluation.EvaluationSettings(num_singles=6))
  assert error.value.field == "default_model_evaluation.num_singles"


@pytest.mark.parametrize("hue_ious, passes", [
    ([0.60, 0.70, 0.80], True),  # 0.80 at scale 1, a rise of 0.20.
    ([0.70, 0.75, 0.80], False),  # The mask, not the control, sets the shape: a rise of 0.10.
    ([0.50, 0.60, 0.70], False),  # Rises, but below the IoU threshold at scale 1.
])
def test_control_gate_needs_both_the_iou_and_the_rise(hue_ious, passes):
  gate = evaluation.control_gate(hue_ious, [0.6, 0.65, 0.7], (0.0, 0.5, 1.0),
                                 evaluation.QualityGates())
  assert gate["passed"] == passes
  assert gate["by_caption_hue"]["rise_from_scale_0"] == pytest.approx(hue_ious[2] - hue_ious[0])
  assert gate["by_difference"]["iou_at_full_scale"] == 0.7


def test_control_gate_needs_scale_zero():
  with pytest.raises(InputError, match="scale 0"):
    evaluation.control_gate([0.7, 0.8], [0.7, 0.8], (0.5, 1.0), evaluation.QualityGates())
