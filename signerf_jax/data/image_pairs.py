"""Which image pairs structure from motion matches (`structure_from_motion`).

Matching every pair costs n (n - 1) / 2 matches; beyond a few hundred images that outgrows the
rest of the processing. Larger captures match each image with its neighbours in capture order
(a video's frames, or a phone's photos, whose names count up as they are taken) and with the
images that look most like it, found by retrieval over visual words (bag of words with tf-idf
weights over the images' own SIFT descriptors, as COLMAP's vocabulary-tree matcher does with a
pretrained tree). Retrieval closes the loop when a walk around an object returns to its start.
"""

from __future__ import annotations

import cv2
import numpy as np

Pair = tuple[int, int]
# Visual words: cluster centres of a sample of the capture's descriptors. 256 words and 40,000
# sampled descriptors take a few seconds to cluster and separate a capture's views well enough
# to find the few most similar (retrieval here needs ranking, not recognition).
VOCABULARY_SIZE = 256
VOCABULARY_SAMPLE = 40_000
VOCABULARY_ITERATIONS = 10


def exhaustive_pairs(num_images: int) -> list[Pair]:
  """Every pair (i, j), i < j, of `num_images` images."""
  return [(i, j) for i in range(num_images) for j in range(i + 1, num_images)]


def sequential_pairs(num_images: int, overlap: int) -> list[Pair]:
  """Each image with the next `overlap` images and, further on, with the images 2^k past it
  (k = log2(overlap) + 1, ...: COLMAP's quadratic overlap), which ties distant parts of a
  sequence together at little cost."""
  pairs = set()
  for i in range(num_images):
    for offset in range(1, overlap + 1):
      if i + offset < num_images:
        pairs.add((i, i + offset))
    offset = 1 << max(overlap, 1).bit_length()
    while i + offset < num_images:
      pairs.add((i, i + offset))
      offset *= 2
  return sorted(pairs)


def retrieval_pairs(descriptors: list[np.ndarray], neighbours: int, seed: int = 0) -> list[Pair]:
  """Each image with the `neighbours` images most similar to it by visual words.

  Args:
    descriptors: per image, [N_i, D] SIFT descriptors (uint8 or float; N_i may be 0).
    neighbours: images retrieved per image.
    seed: of the descriptor sample the vocabulary is clustered from.

  Returns:
    Sorted pairs (i, j), i < j.
  """
  histograms = visual_word_histograms(descriptors, seed)
  similarity = histograms @ histograms.T
  np.fill_diagonal(similarity, -np.inf)
  pairs = set()
  count = min(neighbours, len(descriptors) - 1)
  for i, row in enumerate(similarity):
    for j in np.argsort(-row, kind="stable")[:count]:
      pairs.add((min(i, int(j)), max(i, int(j))))
  return sorted(pairs)


def visual_word_histograms(descriptors: list[np.ndarray], seed: int = 0) -> np.ndarray:
  """[n, VOCABULARY_SIZE] unit-norm tf-idf histograms of each image's visual words (zero rows
  for images without descriptors)."""
  features = [np.asarray(d, np.float32) for d in descriptors]
  everything = np.concatenate([f for f in features if len(f)] or [np.zeros((0, 128), np.float32)])
  if len(everything) == 0:
    return np.zeros((len(features), VOCABULARY_SIZE), np.float32)
  random = np.random.default_rng(seed)
  sample = everything[random.permutation(len(everything))[:VOCABULARY_SAMPLE]]
  words = min(VOCABULARY_SIZE, len(sample))
  cv2.setRNGSeed(seed)
  criteria = (cv2.TERM_CRITERIA_MAX_ITER, VOCABULARY_ITERATIONS, 0)
  _, _, centres = cv2.kmeans(sample, words, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
  counts = np.zeros((len(features), VOCABULARY_SIZE), np.float32)
  for index, feature in enumerate(features):
    if len(feature):
      # Nearest centre by |x|^2 - 2 x.c + |c|^2, dropping |x|^2 (the same for every centre).
      distances = (centres**2).sum(1) - 2.0 * feature @ centres.T
      counts[index] = np.bincount(distances.argmin(1), minlength=VOCABULARY_SIZE)
  # Words that occur in every image say nothing about which images are alike.
  document_frequency = (counts > 0).sum(0)
  inverse_frequency = np.log(len(features) / np.maximum(document_frequency, 1))
  weighted = counts / np.maximum(counts.sum(1, keepdims=True), 1) * inverse_frequency
  norms = np.linalg.norm(weighted, axis=1, keepdims=True)
  return (weighted / np.where(norms > 0, norms, 1)).astype(np.float32)
