"""A word-level tokenizer for small text encoders trained on a closed vocabulary.

Text is lower-cased and split into runs of letters and digits; whitespace and punctuation
(underscores included) only separate words, and anything else (emoji and other symbols,
combining marks, controls) is dropped (`dropped_characters` names it). Each word maps to its id
in the vocabulary, or to the unknown token. `tokenize` lays ids out as the CLIP tokenizer does:
bos, the words (truncated to max_length - 2; `cut_off` names the words cut), eos, then padding,
so the CLIP text encoder's pooling at the first eos works unchanged.

Saved in a checkpoint's `tokenizer/` folder (diffusers layout) as
  vocab.json              {token: id}: the four special tokens, then the words in sorted order;
  tokenizer_config.json   {"tokenizer_class": TOKENIZER_CLASS, "model_max_length", the special
                          tokens, "do_lower_case": true};
  special_tokens_map.json the special tokens.
`signerf_jax.clip.tokenizer.load_tokenizer` recognises the folder by its tokenizer_class.

Special ids: pad 0, unk 1, bos 2, eos 3. The eos id is deliberately not 2: a CLIP text config
with eos_token_id 2 selects transformers' legacy pooling at argmax(ids).
"""

from __future__ import annotations

import os
import re
import unicodedata
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from signerf_jax import files
from signerf_jax.clip import token_ids
from signerf_jax.errors import InputError

TOKENIZER_CLASS = "SignerfWordTokenizer"
SPECIAL_TOKENS = {"pad_token": "<pad>", "unk_token": "<unk>", "bos_token": "<bos>",
                  "eos_token": "<eos>"}
DEFAULT_MAX_LENGTH = 16
VOCABULARY_NAME = "vocab.json"
CONFIG_NAME = "tokenizer_config.json"
SPECIAL_TOKENS_MAP_NAME = "special_tokens_map.json"
_WORD = re.compile(r"[^\W_]+")


def split_words(text: str) -> list[str]:
  """Lower-cased runs of letters and digits: "A red, striped COW!" -> [a, red, striped, cow]."""
  return _WORD.findall(text.lower())


class WordTokenizer:
  """Words -> ids with a fixed vocabulary.

  Attributes:
    vocabulary: token -> id (special tokens included).
    max_length: output length, bos and eos included.
    pad_id, unk_id, bos_id, eos_id: special token ids.
  """

  def __init__(self, vocabulary: dict[str, int], max_length: int = DEFAULT_MAX_LENGTH,
               source: str | os.PathLike | None = None):
    missing = [token for token in SPECIAL_TOKENS.values() if token not in vocabulary]
    if missing:
      raise InputError(f"special tokens {missing} are not in the vocabulary", source, "vocab")
    if sorted(vocabulary.values()) != list(range(len(vocabulary))):
      raise InputError("ids must be 0 .. size - 1, each used once", source, "vocab")
    if max_length < 2:
      raise InputError(f"max_length must leave room for bos and eos, got {max_length}", source,
                       "model_max_length")
    self.vocabulary = dict(vocabulary)
    self.max_length = max_length
    self.pad_id, self.unk_id, self.bos_id, self.eos_id = (
        vocabulary[SPECIAL_TOKENS[name]]
        for name in ("pad_token", "unk_token", "bos_token", "eos_token"))
    self._tokens = {token_id: token for token, token_id in vocabulary.items()}

  @classmethod
  def from_words(cls, words: Iterable[str], max_length: int = DEFAULT_MAX_LENGTH
                 ) -> "WordTokenizer":
    """The vocabulary of every word in `words` (split and lower-cased), after the specials."""
    unique = sorted({word for text in words for word in split_words(text)})
    tokens = [SPECIAL_TOKENS[name] for name in ("pad_token", "unk_token", "bos_token",
                                                "eos_token")] + unique
    return cls({token: token_id for token_id, token in enumerate(tokens)}, max_length)

  @classmethod
  def from_directory(cls, directory: str | os.PathLike) -> "WordTokenizer":
    directory = Path(directory)
    vocabulary = files.read_json(directory / VOCABULARY_NAME)
    if not all(isinstance(token_id, int) for token_id in vocabulary.values()):
      raise InputError("expected a JSON object of token -> integer id", directory / VOCABULARY_NAME)
    config = files.read_json(directory / CONFIG_NAME)
    max_length = config.get("model_max_length")
    if not isinstance(max_length, int):
      raise InputError(f"expected an integer, got {max_length!r}", directory / CONFIG_NAME,
                       "model_max_length")
    for name, token in SPECIAL_TOKENS.items():
      if config.get(name, token) != token:
        raise InputError(f"expected {token!r} (the word tokenizer's fixed special tokens), got "
                         f"{config[name]!r}", directory / CONFIG_NAME, name)
    return cls(vocabulary, max_length, source=directory / VOCABULARY_NAME)

  def save(self, directory: str | os.PathLike) -> None:
    """Writes the three files of the module docstring into `directory` (atomically each)."""
    directory = Path(directory)
    files.write_json(directory / VOCABULARY_NAME, self.vocabulary)
    files.write_json(directory / SPECIAL_TOKENS_MAP_NAME, SPECIAL_TOKENS)
    files.write_json(directory / CONFIG_NAME, {"tokenizer_class": TOKENIZER_CLASS,
                                               "model_max_length": self.max_length,
                                               "do_lower_case": True, **SPECIAL_TOKENS})

  @property
  def vocab_size(self) -> int:
    return len(self.vocabulary)

  def encode(self, text: str) -> list[int]:
    """Ids of the words of `text` (unknown words -> unk), without bos/eos or padding."""
    return [self.vocabulary.get(word, self.unk_id) for word in split_words(text)]

  def unknown_words(self, text: str) -> list[str]:
    """The words of `text` not in the vocabulary (each once, in order)."""
    return list(dict.fromkeys(word for word in split_words(text) if word not in self.vocabulary))

  def dropped_characters(self, text: str) -> list[str]:
    """The characters of `text` the tokenizer drops without a trace (each once, in order): not
    in a word, and neither whitespace nor punctuation, which only separate words. Emoji and
    other symbols, for example."""
    text = text.lower()  # What `split_words` splits (lower-casing may add combining marks).
    in_words = set()
    for match in _WORD.finditer(text):
      in_words.update(range(match.start(), match.end()))
    return list(dict.fromkeys(
        character for index, character in enumerate(text)
        if index not in in_words and not character.isspace()
        and not unicodedata.category(character).startswith("P")))

  def cut_off(self, text: str) -> str:
    """The end of `text` beyond the max_length - 2 words `tokenize` keeps ("" if none)."""
    return token_ids.cut_off_text(text, self.encode, self.max_length)

  @property
  def words(self) -> list[str]:
    """The vocabulary's words, special tokens left out, sorted."""
    specials = set(SPECIAL_TOKENS.values())
    return sorted(token for token in self.vocabulary if token not in specials)

  def tokenize(self, texts: Sequence[str]) -> np.ndarray:
    """[B, max_length] int32: `bos, ids[:max_length - 2], eos, pad, ...` per text."""
    return token_ids.framed_ids(texts, self.encode, self.max_length, self.bos_id, self.eos_id,
                                self.pad_id)

  def decode(self, ids: Sequence[int]) -> str:
    """The words of one id row, special tokens dropped, joined by spaces."""
    specials = (self.pad_id, self.bos_id, self.eos_id)
    return " ".join(self._tokens[int(token_id)] for token_id in ids
                    if int(token_id) not in specials)


def is_word_tokenizer_directory(directory: str | os.PathLike) -> bool:
  """Whether `directory` holds a saved `WordTokenizer` (by its config's tokenizer_class)."""
  config_path = Path(directory) / CONFIG_NAME
  if not config_path.is_file():
    return False
  config = files.read_json(config_path)
  return config.get("tokenizer_class") == TOKENIZER_CLASS
