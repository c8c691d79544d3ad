"""The fixed-length id rows every tokenizer returns: bos, the text's ids, eos, then padding."""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np


def framed_ids(texts: Sequence[str], encode: Callable[[str], list[int]], max_length: int,
               bos_id: int, eos_id: int, pad_id: int) -> np.ndarray:
  """[B, max_length] int32: `bos, encode(text)[:max_length - 2], eos, pad, ...` per text (the eos
  survives truncation)."""
  if isinstance(texts, str):
    raise TypeError("tokenize takes a sequence of texts; wrap a single prompt in a list")
  result = np.full((len(texts), max_length), pad_id, np.int32)
  for row, text in enumerate(texts):
    ids = [bos_id, *encode(text)[:max_length - 2], eos_id]
    result[row, :len(ids)] = ids
  return result
