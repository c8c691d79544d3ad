"""Captions built from an object's attributes, and parsing them back.

A caption names the object's kind (one of its nouns) and, each independently with a set
probability, its colour and its pattern; attributes left out are for the model to choose, which
is what makes the consistency of a multi-view sheet measurable (the prompt does not force it).
Word order: article, "plain" (plain objects), colour, pattern adjective, noun, or with the
pattern as a phrase after the noun:
  "a red striped cow", "a plain red cow", "an orange ball with spots", "a checkered box",
  "a teddy bear".
Empty captions (for classifier-free guidance) are not generated here: dropping the caption is a
training-time choice (replace it by "" with the training's unconditional probability).
"""

from __future__ import annotations

import dataclasses

import gin
import numpy as np

from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import objects
from signerf_jax.metrics import colors

PATTERN_ADJECTIVES = {"plain": "plain", "striped": "striped", "checkered": "checkered",
                      "spotted": "spotted"}
PATTERN_PHRASES = {"striped": "with stripes", "checkered": "with checks", "spotted": "with spots"}


@dataclasses.dataclass(frozen=True)
class Attributes:
  """What an object is; in a parsed caption, None where the caption does not say.

  Attributes:
    kind: an `objects.KINDS` label.
    color: a `metrics.colors.COLORS` name.
    pattern: an `appearance.PATTERNS` name.
  """

  kind: str | None
  color: str | None
  pattern: str | None


@gin.configurable("default_model_captions")
@dataclasses.dataclass(frozen=True)
class CaptionSettings:
  """How often captions mention each attribute (gin: `default_model_captions.<field>`).

  Attributes:
    color_probability: the colour is named.
    pattern_probability: the pattern is named.
    pattern_phrase_probability: a named (non-plain) pattern comes as "with stripes" after the
      noun rather than as an adjective before it.
  """

  color_probability: float = 0.7
  pattern_probability: float = 0.6
  pattern_phrase_probability: float = 0.3


def caption(kind_noun: str, color: str | None, pattern: str | None,
            pattern_as_phrase: bool = False) -> str:
  """The caption naming `kind_noun` and, where not None, `color` and `pattern`."""
  before, after = [], []
  if pattern == "plain":
    before.append(PATTERN_ADJECTIVES[pattern])
  if color is not None:
    before.append(color)
  if pattern not in (None, "plain"):
    (after if pattern_as_phrase else before).append(
        PATTERN_PHRASES[pattern] if pattern_as_phrase else PATTERN_ADJECTIVES[pattern])
  words = " ".join(before + [kind_noun] + after)
  article = "an" if words[0] in "aeiou" else "a"
  return f"{article} {words}"


def random_caption(rng: np.random.Generator, attributes: Attributes,
                   settings: CaptionSettings) -> tuple[str, bool, bool]:
  """A caption for `attributes`: (text, colour named, pattern named)."""
  nouns = objects.KIND_NOUNS[attributes.kind]
  noun = nouns[rng.integers(len(nouns))]
  name_color = bool(rng.uniform() < settings.color_probability)
  name_pattern = bool(rng.uniform() < settings.pattern_probability)
  as_phrase = bool(rng.uniform() < settings.pattern_phrase_probability)
  text = caption(noun, attributes.color if name_color else None,
                 attributes.pattern if name_pattern else None, as_phrase)
  return text, name_color, name_pattern


def _noun_phrases() -> list[tuple[tuple[str, ...], str]]:
  """(noun words, kind), longest first so that "teddy bear" wins over any one-word noun."""
  phrases = [(tuple(word_tokenizer.split_words(noun)), kind)
             for kind, nouns in objects.KIND_NOUNS.items() for noun in nouns]
  return sorted(phrases, key=lambda phrase: -len(phrase[0]))


def parse_caption(text: str) -> Attributes:
  """The kind, colour and pattern a caption names (None for those it does not name)."""
  words = word_tokenizer.split_words(text)
  color = colors.named_color(words)
  pattern = next((name for name, adjective in PATTERN_ADJECTIVES.items() if adjective in words),
                 None)
  for name, phrase in PATTERN_PHRASES.items():
    if phrase.split()[-1] in words:
      pattern = name
  kind = None
  for phrase, name in _noun_phrases():
    if any(tuple(words[start:start + len(phrase)]) == phrase for start in range(len(words))):
      kind = name
      break
  return Attributes(kind=kind, color=color, pattern=pattern)


def vocabulary() -> list[str]:
  """Every word a caption can contain (for the word tokenizer), sorted."""
  texts = ["a an", *colors.COLORS, *PATTERN_ADJECTIVES.values(), *PATTERN_PHRASES.values(),
           *(noun for nouns in objects.KIND_NOUNS.values() for noun in nouns)]
  return sorted({word for text in texts for word in word_tokenizer.split_words(text)})
