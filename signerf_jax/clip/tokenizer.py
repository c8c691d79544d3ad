"""Prompt tokenizers: text -> fixed-length id arrays for the text encoders.

Every tokenizer satisfies the `Tokenizer` protocol (`tokenize(texts) -> [B, max_length] int32`),
so the CLIP BPE tokenizer of Stable Diffusion checkpoints and simpler ones (e.g. a word-level
vocabulary for small models) are interchangeable in `clip.text.encode_prompt`.

`CLIPTokenizer` reproduces transformers' `CLIPTokenizer` from a checkpoint's `vocab.json` +
`merges.txt` (or the same vocabulary and merges in `tokenizer.json`). transformers 5 only has
the tokenizers-library backed class (what diffusers pipelines run); its cleaning differs from
the old slow Python class without ftfy, which also dropped control characters and split CJK
text into single characters. The steps:
  1. special tokens (bos/eos/unk/pad) written literally in the text are split out first (with
     SD 2.x's pad token "!", every "!" of a prompt becomes id 0, as in the reference);
  2. each remaining piece is normalised: Unicode NFC, runs of whitespace -> one space, lower case
     character by character (so a final capital sigma becomes "σ", not "ς");
  3. pre-tokenised with CLIP's pattern
     `<\\|startoftext\\|>|<\\|endoftext\\|>|'s|'t|'re|'ve|'m|'ll|'d|[\\p{L}]+|[\\p{N}]|[^\\s\\p{L}\\p{N}]+`
     (a hand-written scanner over Unicode categories: Python's `re` has no `\\p{..}` classes);
  4. each pre-token is mapped byte-wise to GPT-2's printable byte alphabet, its last symbol gets
     the `</w>` end-of-word suffix, and BPE merges are applied lowest rank first;
  5. `<bos> tokens <eos>`, truncated to `max_length` (the eos is kept; `cut_off` names the end
     cut) and padded with the checkpoint's pad token (`<|endoftext|>` for SD 1.x, `!` = id 0 for
     SD 2.x and SDXL's second tokenizer).
Character classes come from Python's `unicodedata`; characters assigned in a newer Unicode
version than Python's (14.0 for Python 3.11) may be classed differently from the reference.
"""

from __future__ import annotations

import functools
import os
import unicodedata
from pathlib import Path
from typing import Protocol, Sequence

import numpy as np

from signerf_jax import files
from signerf_jax.clip import token_ids
from signerf_jax.clip import word_tokenizer
from signerf_jax.errors import InputError

END_OF_WORD = "</w>"
SPECIAL_LITERALS = ("<|startoftext|>", "<|endoftext|>")  # Alternatives of CLIP's pattern.
CONTRACTIONS = ("'s", "'t", "'re", "'ve", "'m", "'ll", "'d")  # In the pattern's order.
# Oniguruma's `\s` (what the reference's regexes use): Zs/Zl/Zp plus these controls. Python's
# `str.isspace` would also count \x1c-\x1f, which the reference keeps as symbols.
WHITESPACE_CONTROLS = frozenset("\t\n\v\f\r\x85")
DEFAULT_SPECIAL_TOKENS = {"bos_token": "<|startoftext|>", "eos_token": "<|endoftext|>",
                          "unk_token": "<|endoftext|>", "pad_token": "<|endoftext|>"}
DEFAULT_MAX_LENGTH = 77
TOKENIZER_JSON = "tokenizer.json"  # The tokenizers library's single-file format.


class Tokenizer(Protocol):
  """What the prompt encoders need from a tokenizer."""

  max_length: int

  def tokenize(self, texts: Sequence[str]) -> np.ndarray:
    """[B, max_length] int32 ids: bos, tokens, eos, then padding; long texts are truncated."""

  def unknown_words(self, text: str) -> list[str]:
    """The words of `text` the tokenizer can only map to its unknown token."""

  def dropped_characters(self, text: str) -> list[str]:
    """The characters of `text` the text encoder never sees: dropped, or read as the unknown
    token (each once, in order)."""

  def cut_off(self, text: str) -> str:
    """The end of `text` `tokenize` truncates ("" when all of it fits)."""


@functools.cache
def byte_to_symbol() -> dict[int, str]:
  """GPT-2's reversible map from the 256 byte values to printable unicode characters.

  Printable Latin-1 bytes map to themselves; the others are shifted to code points 256+ so that
  no BPE symbol is whitespace or a control character. The order (printable bytes first) is the
  order of the base symbols in CLIP's vocabulary, where "!" is id 0.
  """
  printable = (list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) +
               list(range(ord("®"), ord("ÿ") + 1)))
  symbols = dict(zip(printable, map(chr, printable)))
  shifted = 0
  for byte in range(256):
    if byte not in symbols:
      symbols[byte] = chr(256 + shifted)
      shifted += 1
  return symbols


def _character_class(character: str) -> str:
  """'space', 'letter' (\\p{L}), 'number' (\\p{N}) or 'other', as the reference's regex sees it."""
  category = unicodedata.category(character)
  if character in WHITESPACE_CONTROLS or category in ("Zs", "Zl", "Zp"):
    return "space"
  if category[0] == "L":
    return "letter"
  if category[0] == "N":
    return "number"
  return "other"


def normalize(text: str) -> str:
  """NFC, each run of whitespace -> " ", lower case per character (the reference's normaliser)."""
  text = unicodedata.normalize("NFC", text)
  pieces = []
  previous_was_space = False
  for character in text:
    is_space = _character_class(character) == "space"
    if not (is_space and previous_was_space):
      pieces.append(" " if is_space else character.lower())
    previous_was_space = is_space
  return "".join(pieces)


def pre_tokenize(text: str) -> list[str]:
  """Splits normalised text as CLIP's pattern does (leftmost alternative that matches wins).

  At each position the alternatives are tried in the pattern's order: the literal special
  tokens, the contractions, a run of letters, one digit, a run of anything that is neither space,
  letter nor digit. Whitespace between matches is dropped.
  """
  classes = [_character_class(character) for character in text]
  words = []
  start = 0
  while start < len(text):
    if classes[start] == "space":
      start += 1
      continue
    literal = next((token for token in SPECIAL_LITERALS if text.startswith(token, start)), None)
    if literal is not None:
      # The reference's byte-level stage re-splits every piece with GPT-2's pattern. That is a
      # no-op on all other pieces, but cuts these literals into "<|", the letters and "|>".
      words.extend((literal[:2], literal[2:-2], literal[-2:]))
      start += len(literal)
      continue
    contraction = next((token for token in CONTRACTIONS if text.startswith(token, start)), None)
    if contraction is not None:
      end = start + len(contraction)
    elif classes[start] == "number":
      end = start + 1
    else:
      run_class = classes[start]
      end = start + 1
      while end < len(text) and classes[end] == run_class:
        end += 1
    words.append(text[start:end])
    start = end
  return words


class CLIPTokenizer:
  """Byte-level BPE with `</w>` word ends, as used by CLIP and Stable Diffusion.

  Attributes:
    vocabulary: token string -> id (`vocab.json`).
    merge_ranks: (left id, right id) -> (rank, merged id), from `merges.txt` (rank = line order).
    bos_id, eos_id, pad_id, unk_id: special token ids.
    max_length: output length (77 for every Stable Diffusion text encoder).
  """

  def __init__(self, vocabulary: dict[str, int], merges: Sequence[tuple[str, str]], *,
               bos_token: str = DEFAULT_SPECIAL_TOKENS["bos_token"],
               eos_token: str = DEFAULT_SPECIAL_TOKENS["eos_token"],
               unk_token: str = DEFAULT_SPECIAL_TOKENS["unk_token"],
               pad_token: str = DEFAULT_SPECIAL_TOKENS["pad_token"],
               max_length: int = DEFAULT_MAX_LENGTH, source: str | os.PathLike | None = None):
    def token_id(token: str, field: str) -> int:
      if token not in vocabulary:
        raise InputError(f"{field} {token!r} is not in the vocabulary", source, field)
      return vocabulary[token]

    if max_length < 2:
      raise InputError(f"max_length must leave room for bos and eos, got {max_length}", source,
                       "model_max_length")
    self.vocabulary = vocabulary
    self.bos_id = token_id(bos_token, "bos_token")
    self.eos_id = token_id(eos_token, "eos_token")
    self.unk_id = token_id(unk_token, "unk_token")
    self.pad_id = token_id(pad_token, "pad_token")
    self.special_tokens = tuple(dict.fromkeys((bos_token, eos_token, unk_token, pad_token)))
    self.max_length = max_length
    self.merge_ranks: dict[tuple[int, int], tuple[int, int]] = {}
    for rank, (left, right) in enumerate(merges):
      pair = (token_id(left, "merges"), token_id(right, "merges"))
      self.merge_ranks.setdefault(pair, (rank, token_id(left + right, "merges")))
    self._word_cache: dict[str, tuple[int, ...]] = {}

  @classmethod
  def from_directory(cls, directory: str | os.PathLike) -> "CLIPTokenizer":
    """Reads the vocabulary, merges, special tokens and length of a tokenizer folder.

    The vocabulary and merges come from `vocab.json` + `merges.txt`, or, when those are absent
    (transformers 5 `save_pretrained` writes only this), from the BPE model in `tokenizer.json`.

    Special tokens come from `special_tokens_map.json`, else `tokenizer_config.json`, else the
    CLIP defaults; `model_max_length` from `tokenizer_config.json` (default 77).
    """
    directory = Path(directory)
    if (directory / "vocab.json").is_file() or not (directory / TOKENIZER_JSON).is_file():
      vocabulary = files.read_json(directory / "vocab.json")
      vocabulary_source = directory / "vocab.json"
      merges = read_merges(directory / "merges.txt")
    else:
      vocabulary, merges = _read_tokenizer_json(directory / TOKENIZER_JSON)
      vocabulary_source = directory / TOKENIZER_JSON
    if not isinstance(vocabulary, dict) or not all(
        isinstance(token_id, int) for token_id in vocabulary.values()):
      raise InputError("expected a JSON object of token -> integer id", vocabulary_source,
                       "vocab")
    config_path = directory / "tokenizer_config.json"
    config = files.read_json(config_path) if config_path.is_file() else {}
    special_path = directory / "special_tokens_map.json"
    special_map = files.read_json(special_path) if special_path.is_file() else {}
    special = {}
    for field, default in DEFAULT_SPECIAL_TOKENS.items():
      value = special_map.get(field, config.get(field, default))
      # Serialised AddedToken objects carry the string in "content".
      special[field] = value["content"] if isinstance(value, dict) else value
    max_length = config.get("model_max_length", DEFAULT_MAX_LENGTH)
    if not isinstance(max_length, int):
      raise InputError(f"expected an integer, got {max_length!r}", config_path, "model_max_length")
    return cls(vocabulary, merges, max_length=max_length, source=directory, **special)

  def _word_ids(self, word: str) -> tuple[int, ...]:
    """BPE of one pre-token: repeatedly merge every occurrence of the lowest-ranked pair."""
    cached = self._word_cache.get(word)
    if cached is not None:
      return cached
    encoded = "".join(byte_to_symbol()[byte] for byte in word.encode("utf-8"))
    symbols = list(encoded[:-1]) + [encoded[-1] + END_OF_WORD]
    ids = [self.vocabulary.get(symbol, self.unk_id) for symbol in symbols]
    while len(ids) > 1:
      pairs = [pair for pair in zip(ids, ids[1:]) if pair in self.merge_ranks]
      if not pairs:
        break
      best = min(pairs, key=self.merge_ranks.__getitem__)
      merged = []
      index = 0
      while index < len(ids):
        if tuple(ids[index:index + 2]) == best:
          merged.append(self.merge_ranks[best][1])
          index += 2
        else:
          merged.append(ids[index])
          index += 1
      ids = merged
    self._word_cache[word] = tuple(ids)
    return self._word_cache[word]

  def encode(self, text: str) -> list[int]:
    """Token ids of `text` without bos/eos, truncation or padding."""
    ids = []
    for piece, is_special in _split_special_tokens(text, self.special_tokens):
      if is_special:
        ids.append(self.vocabulary[piece])
        continue
      for word in pre_tokenize(normalize(piece)):
        ids.extend(self._word_ids(word))
    return ids

  def tokenize(self, texts: Sequence[str]) -> np.ndarray:
    """[B, max_length] int32: `bos, ids[:max_length - 2], eos, pad, ...` per text."""
    return token_ids.framed_ids(texts, self.encode, self.max_length, self.bos_id, self.eos_id,
                                self.pad_id)

  def unknown_words(self, text: str) -> list[str]:
    """None: byte-level BPE spells any word out of its pieces (a vocabulary lacking some byte
    makes its characters unknown: `dropped_characters`)."""
    return []

  def dropped_characters(self, text: str) -> list[str]:
    """The characters (normalised) whose bytes are not all in the vocabulary: they become the
    unknown token. None with CLIP's vocabulary, which holds every byte."""
    dropped = []
    for piece, is_special in _split_special_tokens(text, self.special_tokens):
      if is_special:
        continue
      for word in pre_tokenize(normalize(piece)):
        if self.unk_id not in self._word_ids(word):
          continue
        for index, character in enumerate(word):
          symbols = [byte_to_symbol()[byte] for byte in character.encode("utf-8")]
          if index == len(word) - 1:
            symbols[-1] += END_OF_WORD
          if any(symbol not in self.vocabulary for symbol in symbols):
            dropped.append(character)
    return list(dict.fromkeys(dropped))

  def cut_off(self, text: str) -> str:
    """The end of `text` beyond the max_length - 2 tokens `tokenize` keeps ("" if none)."""
    return token_ids.cut_off_text(text, self.encode, self.max_length,
                                  lambda character: _character_class(character) == "space")


def prompt_problems(tokenizer: Tokenizer, text: str) -> list[str]:
  """What of a prompt the text encoder will not read as written, one sentence each: words the
  tokenizer does not know (with the words it knows, when it has a closed vocabulary),
  characters it cannot encode, and the end cut off past its `max_length`. [] when none."""
  problems = []
  unknown = tokenizer.unknown_words(text)
  if unknown:
    known = getattr(tokenizer, "words", None)
    knows = f"; it knows {len(known)} words: {' '.join(known)}" if known is not None else ""
    problems.append(f"the model does not know {', '.join(map(repr, unknown))} (it reads them as "
                    f"its unknown token){knows}")
  dropped = tokenizer.dropped_characters(text)
  if dropped:
    problems.append(f"the model's tokenizer cannot encode {', '.join(map(_describe, dropped))}: "
                    "its text encoder does not see them")
  cut = tokenizer.cut_off(text)
  if cut:
    problems.append(f"longer than the {tokenizer.max_length - 2} tokens the model's text encoder "
                    f"reads: the end {cut!r} is cut off")
  return problems


def _describe(character: str) -> str:
  """A character as an error message shows it: quoted, or by code point and name when it would
  be invisible on its own (a combining mark, a control or format character, a space)."""
  if unicodedata.category(character)[0] not in "MCZ":
    return repr(character)
  name = unicodedata.name(character, "")  # Controls have none.
  return f"U+{ord(character):04X}" + (f" ({name.lower()})" if name else "")


def _split_special_tokens(text: str, special_tokens: Sequence[str]) -> list[tuple[str, bool]]:
  """[(piece, is_special)] with every literal occurrence of a special token split out."""
  pieces = []
  start = 0
  while start < len(text):
    found = [(text.find(token, start), -len(token), token) for token in special_tokens]
    found = [match for match in found if match[0] >= 0]
    if not found:
      break
    position, _, token = min(found)  # Leftmost, then longest.
    if position > start:
      pieces.append((text[start:position], False))
    pieces.append((token, True))
    start = position + len(token)
  if start < len(text):
    pieces.append((text[start:], False))
  return pieces


def read_merges(path: str | os.PathLike) -> list[tuple[str, str]]:
  """`merges.txt`: one "left right" pair per line, lowest rank first; "#version" lines skipped."""
  path = Path(path)
  if not path.is_file():
    raise InputError("file not found", path)
  merges = []
  for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
    if line.startswith("#version"):
      continue
    parts = line.split(" ")
    if len(parts) != 2:
      raise InputError(f"line {number}: expected two symbols separated by one space, got {line!r}",
                       path)
    merges.append((parts[0], parts[1]))
  return merges


def _read_tokenizer_json(path: Path) -> tuple[dict, list[tuple[str, str]]]:
  """(vocabulary, merges) of the BPE model in a tokenizers-library `tokenizer.json`.

  Merges are stored as "left right" strings (tokenizers < 0.20) or [left, right] pairs.
  """
  contents = files.read_json(path)
  model = contents.get("model") if isinstance(contents, dict) else None
  if not isinstance(model, dict) or model.get("type") != "BPE":
    raise InputError("expected a BPE model (CLIP's tokenizer)", path, "model.type")
  merges = []
  for merge in model.get("merges", ()):
    pair = merge.split(" ") if isinstance(merge, str) else merge
    if not isinstance(pair, list) or len(pair) != 2:
      raise InputError(f"expected a pair of symbols, got {merge!r}", path, "model.merges")
    merges.append((pair[0], pair[1]))
  return model.get("vocab"), merges


def load_tokenizer(directory: str | os.PathLike) -> Tokenizer:
  """The tokenizer stored in a checkpoint's `tokenizer/` or `tokenizer_2/` folder."""
  directory = Path(directory)
  if not directory.is_dir():
    raise InputError("tokenizer directory not found", directory)
  if (((directory / "vocab.json").is_file() and (directory / "merges.txt").is_file())
      or (directory / TOKENIZER_JSON).is_file()):
    return CLIPTokenizer.from_directory(directory)
  if word_tokenizer.is_word_tokenizer_directory(directory):
    return word_tokenizer.WordTokenizer.from_directory(directory)
  raise InputError("no tokenizer found: expected vocab.json and merges.txt or tokenizer.json "
                   "(CLIP BPE), or a word-level tokenizer_config.json", directory)
