"""Word-level tokenizer: layout, round trip, unknown words, saving and detection by load_tokenizer."""

import json

import numpy as np
import pytest

from signerf_jax.clip import text as clip_text
from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import captions
from signerf_jax.errors import InputError


@pytest.fixture
def tokenizer():
  return word_tokenizer.WordTokenizer.from_words(["a red striped cow", "an orange ball"],
                                                 max_length=8)


def test_ids_are_bos_words_eos_then_padding(tokenizer):
  ids = tokenizer.tokenize(["A RED cow", ""])
  vocabulary = tokenizer.vocabulary
  assert ids.dtype == np.int32 and ids.shape == (2, 8)
  np.testing.assert_array_equal(ids[0], [tokenizer.bos_id, vocabulary["a"], vocabulary["red"],
                                         vocabulary["cow"], tokenizer.eos_id] + [tokenizer.pad_id] * 3)
  np.testing.assert_array_equal(ids[1], [tokenizer.bos_id, tokenizer.eos_id] + [tokenizer.pad_id] * 6)


@pytest.mark.parametrize("text, words", [
    ("a red striped cow", "a red striped cow"),
    ("  A Red,STRIPED   cow!! ", "a red striped cow"),
    ("an_orange-ball.", "an orange ball"),
])
def test_round_trip_lowercases_and_splits_on_punctuation(tokenizer, text, words):
  assert tokenizer.decode(tokenizer.tokenize([text])[0]) == words


def test_unknown_words_map_to_unk(tokenizer):
  ids = tokenizer.tokenize(["a purple zebra cow"])[0]
  assert list(ids[1:6]) == [tokenizer.vocabulary["a"], tokenizer.unk_id, tokenizer.unk_id,
                            tokenizer.vocabulary["cow"], tokenizer.eos_id]
  assert tokenizer.decode(ids) == "a <unk> <unk> cow"


def test_long_texts_are_truncated_keeping_eos(tokenizer):
  ids = tokenizer.tokenize(["red " * 20])[0]
  assert list(ids) == [tokenizer.bos_id] + [tokenizer.vocabulary["red"]] * 6 + [tokenizer.eos_id]


def test_eos_id_avoids_clips_legacy_pooling(tokenizer):
  # A CLIP text config with eos_token_id 2 pools at argmax(ids) instead of the first eos.
  assert tokenizer.eos_id != clip_text.LEGACY_EOS_TOKEN_ID
  assert tokenizer.vocabulary["<pad>"] == 0


def test_saved_tokenizer_is_found_by_load_tokenizer(tmp_path):
  original = word_tokenizer.WordTokenizer.from_words(captions.vocabulary())
  original.save(tmp_path)
  loaded = tokenizer_lib.load_tokenizer(tmp_path)
  assert isinstance(loaded, word_tokenizer.WordTokenizer)
  assert loaded.vocabulary == original.vocabulary and loaded.max_length == 16
  texts = ["a red striped cow", "an orange teddy bear with spots", "a plain box"]
  np.testing.assert_array_equal(loaded.tokenize(texts), original.tokenize(texts))
  assert original.unk_id not in original.tokenize(texts)


def test_bad_tokenizer_files_raise_input_errors(tmp_path):
  word_tokenizer.WordTokenizer.from_words(["a cow"]).save(tmp_path)
  vocabulary_path = tmp_path / word_tokenizer.VOCABULARY_NAME
  vocabulary_path.write_text(json.dumps({"a": 0, "cow": 1}))
  with pytest.raises(InputError, match="special tokens"):
    tokenizer_lib.load_tokenizer(tmp_path)
  vocabulary_path.write_text(json.dumps({"<pad>": 0, "<unk>": 1, "<bos>": 2, "<eos>": 5}))
  with pytest.raises(InputError, match="ids must be"):
    tokenizer_lib.load_tokenizer(tmp_path)
  (tmp_path / word_tokenizer.CONFIG_NAME).write_text(json.dumps({"tokenizer_class": "Other"}))
  with pytest.raises(InputError, match="no tokenizer found"):
    tokenizer_lib.load_tokenizer(tmp_path)


@pytest.mark.parametrize("text, dropped", [
    ("a red cow", []),
    ("  A Red,STRIPED   cow!! an_orange-ball. (yes?) 'q'", []),  # Whitespace, punctuation.
    ("a red 🐄 cow ✨🐄", ["🐄", "✨"]),
    ("cow 👩‍👩‍👧", ["👩", "\u200d", "👧"]),  # Zero-width joiners too.
    ("a $5 + cow", ["$", "+"]),
    ("cafe\u0301", ["\u0301"]),  # A combining accent splits the word, and is lost.
])
def test_dropped_characters_are_what_splitting_into_words_loses(tokenizer, text, dropped):
  assert tokenizer.dropped_characters(text) == dropped


@pytest.mark.parametrize("text, cut", [
    ("a red striped cow", ""),
    ("a red striped cow an orange", ""),  # Six words: exactly max_length - 2.
    ("a, red, striped, cow, an, orange, ball!", "ball!"),
    ("red " * 20, " ".join(["red"] * 14)),
    ("a red 🐄 striped cow an orange ball x", "ball x"),  # The emoji is no word.
])
def test_cut_off_is_the_end_tokenize_leaves_out(tokenizer, text, cut):
  assert tokenizer.cut_off(text) == cut
  kept = text[:text.rindex(cut)] if cut else text
  np.testing.assert_array_equal(tokenizer.tokenize([kept]), tokenizer.tokenize([text]))


def test_prompt_problems_name_unknown_words_dropped_characters_and_the_cut_end(tokenizer):
  assert tokenizer_lib.prompt_problems(tokenizer, "a red cow") == []
  problems = tokenizer_lib.prompt_problems(
      tokenizer, "a red 🐄 zebra cow, a striped cow an orange ball")
  assert problems == [
      "the model does not know 'zebra' (it reads them as its unknown token); it knows 7 words: "
      "a an ball cow orange red striped",
      "the model's tokenizer cannot encode '🐄': its text encoder does not see them",
      "longer than the 6 tokens the model's text encoder reads: the end 'cow an orange ball' is "
      "cut off"]
