"""Silhouette metrics: IoU, pooled precision and recall, and the speck/hole clean-up."""

import numpy as np

from signerf_jax.metrics import silhouettes


def test_silhouette_iou_known_values():
  left, right = np.zeros((2, 8, 8), bool), np.zeros((2, 8, 8), bool)
  left[0, 2:6, 0:4] = True
  right[0, 2:6, 2:6] = True  # Overlap of 8 pixels, union of 24.
  ious = silhouettes.silhouette_iou(np.concatenate([left, left[:1], right[:1]]),
                                   np.concatenate([right, left[:1], np.zeros((1, 8, 8), bool)]))
  np.testing.assert_allclose(ious, [1 / 3, 1.0, 1.0, 0.0])  # Both empty counts as 1.



def test_pooled_precision_recall_pools_pixels_over_views():
  predicted, target = np.zeros((2, 4, 4), bool), np.zeros((2, 4, 4), bool)
  predicted[0, :2] = True  # 8 pixels, 4 of them right.
  target[0, :1] = True
  target[1, :1] = True  # 4 more to find, none found.
  precision, recall = silhouettes.pooled_precision_recall(predicted, target)
  assert precision == 4 / 8 and recall == 4 / 8
  assert np.isnan(silhouettes.pooled_precision_recall(np.zeros((1, 4, 4), bool), target[:1])[0])
  assert np.isnan(silhouettes.pooled_precision_recall(predicted[:1], np.zeros((1, 4, 4), bool))[1])


def test_specks_are_dropped_and_small_holes_filled():
  view = np.zeros((1, 12, 12), bool)
  view[0, 2:10, 2:10] = True
  view[0, 5, 5] = False  # A one-pixel hole.
  view[0, 0, 11] = True  # A one-pixel speck.
  cleaned = silhouettes.without_specks(view, min_pixels=4)
  expected = np.zeros((12, 12), bool)
  expected[2:10, 2:10] = True
  np.testing.assert_array_equal(cleaned[0], expected)
