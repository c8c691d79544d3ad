"""Captions: every form parses back to the attributes it names; the vocabulary covers them."""

import numpy as np
import pytest

from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import appearance, captions, objects
from signerf_jax.metrics import colors

ALL_FORMS = [(kind, noun, color, pattern, phrase)
             for kind, nouns in objects.KIND_NOUNS.items() for noun in nouns
             for color in (None, *colors.COLORS) for pattern in (None, *appearance.PATTERNS)
             for phrase in (False, True)]


def test_every_caption_parses_back_to_its_attributes():
  vocabulary = set(captions.vocabulary())
  for kind, noun, color, pattern, phrase in ALL_FORMS:
    text = captions.caption(noun, color, pattern, phrase)
    assert captions.parse_caption(text) == captions.Attributes(kind, color, pattern), text
    assert set(word_tokenizer.split_words(text)) <= vocabulary, text


@pytest.mark.parametrize("attributes, text", [
    (("cow", "red", "striped", False), "a red striped cow"),
    (("cow", "red", "striped", True), "a red cow with stripes"),
    (("ball", "orange", "plain", True), "a plain orange ball"),
    (("teddy bear", None, "spotted", True), "a teddy bear with spots"),
    (("cube", "orange", None, False), "an orange cube"),
])
def test_word_order_and_articles(attributes, text):
  assert captions.caption(*attributes) == text


def test_parse_ignores_case_punctuation_and_unknown_words():
  parsed = captions.parse_caption("A big RED, shiny Teddy Bear -- with Stripes!")
  assert parsed == captions.Attributes("teddy", "red", "striped")
  assert captions.parse_caption("something else") == captions.Attributes(None, None, None)


def test_random_captions_name_attributes_at_the_set_rates():
  settings = captions.CaptionSettings(color_probability=0.7, pattern_probability=0.4)
  rng = np.random.default_rng(0)
  attributes = captions.Attributes("cow", "blue", "checkered")
  drawn = [captions.random_caption(rng, attributes, settings) for _ in range(2000)]
  names_color = np.mean([named for _, named, _ in drawn])
  names_pattern = np.mean([named for _, _, named in drawn])
  assert abs(names_color - 0.7) < 0.04 and abs(names_pattern - 0.4) < 0.04
  for text, named_color, named_pattern in drawn:
    parsed = captions.parse_caption(text)
    assert parsed.kind == "cow"
    assert parsed.color == ("blue" if named_color else None)
    assert parsed.pattern == ("checkered" if named_pattern else None)
  # Both attributes, one, and none all occur: the model must sometimes choose.
  assert len({(named_color, named_pattern) for _, named_color, named_pattern in drawn}) == 4
