"""The fixed-length id rows every tokenizer returns: bos, the text's ids, eos, then padding; and
what of a text they leave out."""

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


def cut_off_text(text: str, encode: Callable[[str], list[int]], max_length: int,
                 is_space: Callable[[str], bool] = str.isspace) -> str:
  """The end of `text` that `framed_ids` cuts off: "" when its ids fit in max_length - 2, else
  from the first word (a run of characters between `is_space` ones) whose ids do not all fit.

  `encode` must split words only at spaces (the ids of a text are its words' ids in order), as
  both tokenizers' do: the words are encoded one by one and counted.
  """
  room = max_length - 2
  if len(encode(text)) <= room:
    return ""
  used = 0
  start = None
  for index, character in enumerate(text + " "):
    if not is_space(character) and index < len(text):
      start = index if start is None else start
      continue
    if start is not None:
      used += len(encode(text[start:index]))
      if used > room:
        return text[start:].strip()
      start = None
  return text.strip()  # Unreachable for the tokenizers here; all of it rather than nothing.
