"""experiments/results/README.md indexes the committed results: every file it lists exists, every
file in the folder is listed, and the folder stays small enough to clone (issue 69: 15 MB)."""

from __future__ import annotations

import re
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "experiments" / "results"
INDEX = RESULTS / "README.md"
MAX_BYTES = 15 * 1024 * 1024


def listed_files() -> list[str]:
  """The file names in backticks in the first cell of each row of the index's table."""
  names = []
  for line in INDEX.read_text().splitlines():
    cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
    if not line.startswith("|") or set(cells[0]) <= set("- :") or cells[0] == "Files":
      continue  # Not a table row, or the header or its separator.
    row = re.findall(r"`([^`]+)`", cells[0])
    assert row, f"an index row names no file: {line[:80]}"
    names += row
  return names


def test_the_index_lists_files():
  assert len(listed_files()) > 10


def test_every_listed_file_exists():
  missing = [name for name in listed_files() if not (RESULTS / name).is_file()]
  assert not missing, f"listed in {INDEX.name} but not in {RESULTS}: {missing}"


def test_every_file_is_listed_once():
  names = listed_files()
  assert len(names) == len(set(names)), sorted({name for name in names if names.count(name) > 1})
  present = {path.name for path in RESULTS.iterdir() if path != INDEX}
  unlisted = sorted(present - set(names))
  assert not unlisted, f"in {RESULTS} but not listed in {INDEX.name}: {unlisted}"


def test_the_folder_stays_small():
  size = sum(path.stat().st_size for path in RESULTS.rglob("*") if path.is_file())
  assert size <= MAX_BYTES, f"{RESULTS} holds {size / 2**20:.1f} MiB (at most 15)"
