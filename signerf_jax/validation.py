"""Type and range checks of the settings dataclasses, declared by their annotations.

A settings field says what it accepts in its type: `steps: PositiveInt`, `strength:
Annotated[float, Range(0, 1)]`, `kind: Literal["box", "proxy"]`, `up: Vector3 | None`. Each
settings class calls `check_fields(self)` first thing in `__post_init__`, so a value from gin, a
command-line flag or Python is checked when the settings are built, before any work starts, and
the error names the parameter, the value and what is allowed:

    TrainConfig.steps: must be an integer >= 1, got -5

Checks that relate two fields (min <= max) stay in the class's own `__post_init__`.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import numbers
import types
import typing
from typing import Annotated, Any, Literal, Mapping, Union

from signerf_jax.errors import InputError


@dataclasses.dataclass(frozen=True)
class Range:
  """The interval a number must lie in; a missing bound is unbounded.

  Attributes:
    low, high: the bounds (None: none).
    low_inclusive, high_inclusive: whether a bound itself is allowed.
  """

  low: float | None = None
  high: float | None = None
  low_inclusive: bool = True
  high_inclusive: bool = True

  def contains(self, value: float) -> bool:
    if self.low is not None and not (value >= self.low if self.low_inclusive
                                     else value > self.low):
      return False
    return self.high is None or (value <= self.high if self.high_inclusive
                                 else value < self.high)

  def __str__(self) -> str:
    if self.low is not None and self.high is not None:
      return (f"in {'[' if self.low_inclusive else '('}{self.low:g}, {self.high:g}"
              f"{']' if self.high_inclusive else ')'}")
    if self.low is not None:
      return f"{'>=' if self.low_inclusive else '>'} {self.low:g}"
    return f"{'<=' if self.high_inclusive else '<'} {self.high:g}"


PositiveInt = Annotated[int, Range(1)]
NonNegativeInt = Annotated[int, Range(0)]
PositiveFloat = Annotated[float, Range(0, low_inclusive=False)]
NonNegativeFloat = Annotated[float, Range(0)]
UnitInterval = Annotated[float, Range(0, 1)]
OpenUnitInterval = Annotated[float, Range(0, 1, low_inclusive=False, high_inclusive=False)]
Vector3 = tuple[float, float, float]
Color = tuple[UnitInterval, UnitInterval, UnitInterval]


class CheckedFields:
  """Base of the settings dataclasses: building one checks every field against its annotation
  (`check_fields`), so gin, flags and Python calls are all checked before any work. A subclass
  with rules across fields calls `super().__post_init__()` first."""

  def __post_init__(self):
    check_fields(self)


def check_fields(config: Any) -> None:
  """Checks every field of the dataclass instance `config` against its annotation.

  Lists given for tuple fields (gin reads `[1, 2]` as a list) become tuples.
  Raises:
    InputError naming `<class>.<field>`, the value and what the annotation allows.
  """
  hints = _type_hints(type(config))
  for field in dataclasses.fields(config):
    value = getattr(config, field.name)
    matches, normalised = _match(value, hints[field.name])
    if not matches:
      shown = repr(value)
      shown = shown if len(shown) <= 80 else shown[:77] + "..."
      raise InputError(f"must be {describe(hints[field.name])}, got {shown}",
                       field=f"{type(config).__name__}.{field.name}")
    if normalised is not value:  # Frozen: set through object, as dataclasses itself does.
      object.__setattr__(config, field.name, normalised)


def describe(hint: Any) -> str:
  """What a type annotation allows, in words ("an integer >= 1 or None")."""
  origin, arguments = typing.get_origin(hint), typing.get_args(hint)
  if origin is Annotated:
    return " ".join([describe(arguments[0])] + [str(rule) for rule in arguments[1:]])
  if origin in (Union, types.UnionType):
    return " or ".join(describe(option) for option in arguments)
  if origin is Literal:
    return "one of " + ", ".join(repr(choice) for choice in arguments)
  if origin is tuple:
    if len(arguments) == 2 and arguments[1] is Ellipsis:
      return f"a tuple whose items are each {describe(arguments[0])}"
    if len(set(arguments)) == 1:
      return f"a tuple of {len(arguments)} items, each {describe(arguments[0])}"
    return "a tuple (" + ", ".join(describe(item) for item in arguments) + ")"
  names = {type(None): "None", bool: "True or False", int: "an integer",
           float: "a finite number", str: "a string", Any: "anything"}
  if hint in names:
    return names[hint]
  if origin is not None and issubclass(origin, Mapping):
    return "a mapping from names to values"
  raise TypeError(f"no check for the annotation {hint!r}")


def check_value(value: Any, hint: Any, path: Any = None, field: str | None = None) -> Any:
  """`value` (lists made tuples) when the annotation `hint` allows it, for a value read from a
  file rather than a settings field; else InputError naming `path` and `field`."""
  matches, normalised = _match(value, hint)
  if not matches:
    raise InputError(f"must be {describe(hint)}, got {value!r}", path, field)
  return normalised


def argument_type(hint: Any, field: str | None = None):
  """An argparse `type=` that parses a flag's text and checks it against a type annotation.

  Args:
    hint: an annotation (`PositiveInt`, `float`), or a settings class whose `field`'s
      annotation the flag shares (one rule per parameter: `argument_type(TrainConfig,
      "steps")`). `X | None` checks X; a tuple of one item type checks each of the flag's
      `nargs` values as that type.
  Returns:
    the parser; a bad value fails with argparse's usage error, e.g. "argument --chunk_size:
    must be an integer >= 1, got 0".
  """
  if field is not None:
    hint = _type_hints(hint)[field]
  if typing.get_origin(hint) in (Union, types.UnionType):
    hint, = [option for option in typing.get_args(hint) if option is not type(None)]
  if typing.get_origin(hint) is tuple:
    hint = typing.get_args(hint)[0]
  base = typing.get_args(hint)[0] if typing.get_origin(hint) is Annotated else hint

  def parse(text: str):
    try:
      value = base(text)
    except ValueError:
      raise argparse.ArgumentTypeError(f"must be {describe(hint)}, got {text!r}") from None
    if not _match(value, hint)[0]:
      raise argparse.ArgumentTypeError(f"must be {describe(hint)}, got {text}")
    return value

  return parse


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
  # Modules use `from __future__ import annotations`: the annotations are strings until now.
  return typing.get_type_hints(cls, include_extras=True)


def _match(value: Any, hint: Any) -> tuple[bool, Any]:
  """(whether `value` is allowed by `hint`, the value with lists turned into tuples)."""
  origin, arguments = typing.get_origin(hint), typing.get_args(hint)
  if origin is Annotated:
    matches, value = _match(value, arguments[0])
    return matches and all(rule.contains(value) for rule in arguments[1:]), value
  if origin in (Union, types.UnionType):
    for option in arguments:
      matches, normalised = _match(value, option)
      if matches:
        return True, normalised
    return False, value
  if origin is Literal:
    return any(type(value) is type(choice) and value == choice for choice in arguments), value
  if origin is tuple:
    return _match_tuple(value, arguments)
  if hint is type(None):
    return value is None, value
  if hint is bool:
    return isinstance(value, bool), value
  if hint is int:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool), value
  if hint is float:
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and math.isfinite(value)), value
  if hint is str:
    return isinstance(value, str), value
  if hint is Any:
    return True, value
  if origin is not None and issubclass(origin, Mapping):
    return isinstance(value, Mapping) and all(isinstance(key, str) for key in value), value
  raise TypeError(f"no check for the annotation {hint!r}")


def _match_tuple(value: Any, arguments: tuple[Any, ...]) -> tuple[bool, Any]:
  if not isinstance(value, (tuple, list)):
    return False, value
  if len(arguments) == 2 and arguments[1] is Ellipsis:
    arguments = (arguments[0],) * len(value)
  if len(value) != len(arguments):
    return False, value
  items = [_match(item, hint) for item, hint in zip(value, arguments)]
  if not all(matches for matches, _ in items):
    return False, value
  normalised = tuple(item for _, item in items)
  unchanged = isinstance(value, tuple) and all(a is b for a, b in zip(normalised, value))
  return True, value if unchanged else normalised
