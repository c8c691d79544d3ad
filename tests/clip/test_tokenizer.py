"""CLIP BPE tokenizer: parity with transformers' CLIPTokenizer on a small trained vocabulary."""

import collections
import json

import numpy as np
import pytest

from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.errors import InputError

TRAINING_TEXT = """a photo of an astronaut riding a horse on the moon, highly detailed, trending on
artstation. the quick brown fox jumps over the lazy dog; photograph, portrait painting of a cat
wearing a hat. café naïve résumé über straße 東京 タワー 猫 🐱 🚀 it's don't we're they've i'm
we'll you'd. teddy bear sitting on a bench in the park, 4k, 8k, unreal engine, octane render"""

PROMPTS = [
    "a photo of an astronaut riding a horse on the moon",
    "A PHOTO of an AsTrOnAuT, Riding!! a horse...?!",
    "",
    "   \t\n ",
    "It's DON'T we're They've I'M we'll you'd 'S x's'll",
    "Café naïve RÉSUMÉ Über STRASSE straße cafe\u0301",  # Composed and decomposed accents.
    "東京タワー 猫🐱🚀 family 👩‍👩‍👧 flags 🇫🇷",  # CJK, emoji, zero-width joiners.
    "ΟΔΟΣ Σ σς İstanbul ǅ ﬁ Ⅻ ½ ²",  # Per-character lower casing, letter-like numbers.
    "numbers 12345 3.14 1,000 4k 8K",
    "tabs\tand\nnewlines\r\n  nbsp\u00a0ideographic\u3000em\u2003space",
    "\x1cunit\x1dseparators\x1f zero\u200bwidth ctrl\x00\x07",
    "hello...!!!???---___*** 'quoted' word's !'s",
    "a<|endoftext|>b <|startoftext|>x <|ENDOFTEXT|>!! wow !! x!",  # Special tokens in the text.
    "हिन्दी mixed123abc",
    "teddy bear on a bench " * 20,  # Longer than 77 tokens: truncated.
]


def byte_level_word(word: str) -> tuple[str, ...]:
  symbols = "".join(tokenizer_lib.byte_to_symbol()[byte] for byte in word.encode("utf-8"))
  return (*symbols[:-1], symbols[-1] + "</w>")


def train_bpe(words: list[str], num_merges: int) -> tuple[dict[str, int], list[tuple[str, str]]]:
  """Textbook BPE training: repeatedly merge the most frequent adjacent pair (CLIP's layout)."""
  base = list(tokenizer_lib.byte_to_symbol().values())
  vocabulary = base + [symbol + "</w>" for symbol in base]
  corpus = collections.Counter(byte_level_word(word) for word in words)
  merges = []
  for _ in range(num_merges):
    pairs = collections.Counter()
    for word, count in corpus.items():
      for pair in zip(word, word[1:]):
        pairs[pair] += count
    if not pairs:
      break
    best = max(pairs, key=lambda pair: (pairs[pair], pair))
    merges.append(best)
    vocabulary.append("".join(best))
    merged_corpus = collections.Counter()
    for word, count in corpus.items():
      symbols, index = [], 0
      while index < len(word):
        if word[index:index + 2] == best:
          symbols.append("".join(best))
          index += 2
        else:
          symbols.append(word[index])
          index += 1
      merged_corpus[tuple(symbols)] += count
    corpus = merged_corpus
  vocabulary += ["<|startoftext|>", "<|endoftext|>"]
  return {token: index for index, token in enumerate(vocabulary)}, merges


def write_tokenizer(directory, vocabulary, merges, config=None, special_tokens_map=None):
  directory.mkdir(parents=True)
  (directory / "vocab.json").write_text(json.dumps(vocabulary, ensure_ascii=False), "utf-8")
  (directory / "merges.txt").write_text(
      "#version: 0.2\n" + "".join(f"{left} {right}\n" for left, right in merges), "utf-8")
  if config is not None:
    (directory / "tokenizer_config.json").write_text(json.dumps(config))
  if special_tokens_map is not None:
    (directory / "special_tokens_map.json").write_text(json.dumps(special_tokens_map))
  return directory


def added_token(content):
  """How transformers serialises special tokens in tokenizer_config.json."""
  return {"__type": "AddedToken", "content": content, "lstrip": False, "normalized": True,
          "rstrip": False, "single_word": False}


@pytest.fixture(scope="module")
def vocabulary_and_merges():
  words = TRAINING_TEXT.replace(",", " ").replace(".", " ").replace(";", " ").split()
  return train_bpe(words * 3 + ["photograph", "astronaut"] * 5, num_merges=400)


@pytest.fixture(scope="module", params=["sd1", "sd2"])
def tokenizer_directory(request, tmp_path_factory, vocabulary_and_merges):
  """SD 1.x pads with the eos token; SD 2.x / SDXL's second tokenizer pads with "!" (id 0)."""
  directory = tmp_path_factory.mktemp("tokenizers") / request.param
  if request.param == "sd1":
    config = {"bos_token": added_token("<|startoftext|>"),
              "eos_token": added_token("<|endoftext|>"),
              "unk_token": added_token("<|endoftext|>"), "pad_token": "<|endoftext|>",
              "model_max_length": 77, "do_lower_case": True}
    return write_tokenizer(directory, *vocabulary_and_merges, config=config)
  return write_tokenizer(directory, *vocabulary_and_merges, config={"model_max_length": 77},
                         special_tokens_map={"pad_token": "!"})


@pytest.mark.parity
def test_ids_match_transformers(tokenizer_directory):
  transformers = pytest.importorskip("transformers")
  reference = transformers.CLIPTokenizer.from_pretrained(str(tokenizer_directory))
  ours = tokenizer_lib.load_tokenizer(tokenizer_directory)
  assert ours.pad_id == reference.pad_token_id and ours.max_length == 77
  expected = reference(PROMPTS, padding="max_length", max_length=77, truncation=True).input_ids
  ids = ours.tokenize(PROMPTS)
  assert ids.dtype == np.int32 and ids.shape == (len(PROMPTS), 77)
  for prompt, row, expected_row in zip(PROMPTS, ids.tolist(), expected):
    assert row == expected_row, prompt


def test_words_are_merged_into_multi_symbol_tokens(tokenizer_directory):
  """The vocabulary is real BPE: common words become one token, rarer ones several."""
  tokens = tokenizer_lib.load_tokenizer(tokenizer_directory)
  inverse = {index: token for token, index in tokens.vocabulary.items()}
  assert [inverse[i] for i in tokens.encode("Astronaut photograph")] == [
      "astronaut</w>", "photograph</w>"]
  pieces = [inverse[i] for i in tokens.encode("astrophotography")]
  assert 1 < len(pieces) < len("astrophotography") and pieces[-1].endswith("</w>")
  assert "".join(pieces) == "astrophotography</w>"


def test_padding_truncation_and_empty_prompt(tokenizer_directory):
  tokens = tokenizer_lib.load_tokenizer(tokenizer_directory)
  empty, long = tokens.tokenize(["", "moon " * 100])
  assert empty[:2].tolist() == [tokens.bos_id, tokens.eos_id]
  assert (empty[2:] == tokens.pad_id).all()
  assert long[0] == tokens.bos_id and long[-1] == tokens.eos_id
  assert (long[1:-1] == tokens.encode("moon")[0]).all()


def test_sd2_pad_token_is_exclamation_mark_id_zero(tokenizer_directory):
  tokens = tokenizer_lib.load_tokenizer(tokenizer_directory)
  expected = 0 if tokenizer_directory.name == "sd2" else tokens.eos_id
  assert tokens.pad_id == expected


@pytest.mark.parametrize("text, words", [
    ("it's a dog's life", ["it", "'s", "a", "dog", "'s", "life"]),
    ("4k8k", ["4", "k", "8", "k"]),
    ("wow!!! ?", ["wow", "!!!", "?"]),
    ("x<|endoftext|>!!", ["x", "<|", "endoftext", "|>", "!!"]),
    ("東京タワー", ["東京タワー"]),
    ("\x1c a", ["\x1c", "a"]),  # Not whitespace for the reference, unlike Python's isspace.
])
def test_pre_tokenize(text, words):
  assert tokenizer_lib.pre_tokenize(tokenizer_lib.normalize(text)) == words


def test_normalize():
  assert tokenizer_lib.normalize("A\t\n B\u3000ΟΔΟΣ cafe\u0301") == "a b οδοσ café"


def test_bad_files_name_the_file_and_field(tmp_path, vocabulary_and_merges):
  vocabulary, merges = vocabulary_and_merges
  with pytest.raises(InputError, match="tokenizer directory not found"):
    tokenizer_lib.load_tokenizer(tmp_path / "absent")
  directory = write_tokenizer(tmp_path / "bad_pad", vocabulary, merges,
                              special_tokens_map={"pad_token": "<pad>"})
  with pytest.raises(InputError, match="'<pad>' is not in the vocabulary") as error:
    tokenizer_lib.load_tokenizer(directory)
  assert error.value.field == "pad_token"
  directory = write_tokenizer(tmp_path / "bad_merges", vocabulary, [("a", "b c")])
  with pytest.raises(InputError, match="line 2") as error:
    tokenizer_lib.load_tokenizer(directory)
  assert error.value.path.endswith("merges.txt")
  directory = write_tokenizer(tmp_path / "unknown_merge", vocabulary, [("q", "zz")])
  with pytest.raises(InputError, match="'zz' is not in the vocabulary"):
    tokenizer_lib.load_tokenizer(directory)


def test_cut_off_is_the_end_tokenize_leaves_out(vocabulary_and_merges):
  tokens = tokenizer_lib.CLIPTokenizer(*vocabulary_and_merges, max_length=8)
  assert tokens.cut_off("Astronaut photograph") == ""
  assert tokens.cut_off("astronaut photograph " * 5) == "astronaut photograph astronaut photograph"
  long = tokenizer_lib.CLIPTokenizer(*vocabulary_and_merges)
  for text in PROMPTS:
    cut = long.cut_off(text)
    kept = text[:text.rindex(cut)] if cut else text
    assert len(long.encode(kept)) <= 75, text
    if cut:  # The first word cut off does not fit whole.
      assert len(long.encode(kept + cut.split()[0])) > 75, text
  assert long.cut_off(PROMPTS[-1]).endswith("teddy bear on a bench")


def test_characters_outside_the_vocabulary_are_named(vocabulary_and_merges):
  vocabulary, merges = vocabulary_and_merges
  tokens = tokenizer_lib.CLIPTokenizer(vocabulary, merges)
  assert tokens.dropped_characters("a cow 🐄 東京 \x07") == []  # Every byte is in CLIP's.
  # Without the symbol of byte 0xf0 (every emoji's first), emoji become the unknown token.
  missing = tokenizer_lib.byte_to_symbol()[0xf0]
  reduced = {token: index for token, index in vocabulary.items() if missing not in token}
  kept = [(left, right) for left, right in merges if missing not in left + right]
  tokens = tokenizer_lib.CLIPTokenizer(reduced, kept)
  assert tokens.dropped_characters("a cow 🐄, a 🚀🐄 東京") == ["🐄", "🚀"]
  assert tokens.unk_id in tokens.encode("🐄")
  assert tokenizer_lib.prompt_problems(tokens, "a cow 🐄") == [
      "the model's tokenizer cannot encode '🐄': its text encoder does not see them"]
