"""The one exception type for bad user input: it names the file and the field at fault."""

from __future__ import annotations

import os


class InputError(ValueError):
  """Bad input (a file, a field in it, a parameter), reported so the user can fix it.

  The message reads `<path>: <field>: <problem>`; `path` and `field` stay available as
  attributes so callers and tests can check what was blamed.
  """

  def __init__(self, problem: str, path: str | os.PathLike | None = None,
               field: str | None = None):
    self.path = None if path is None else os.fspath(path)
    self.field = field
    self.problem = problem
    location = [part for part in (self.path, field) if part]
    super().__init__(": ".join(location + [problem]))
