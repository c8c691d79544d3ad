"""The README is for users: short, with figures shown inline, and every file it shows or links
to exists."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
MAX_LINES = 300


def test_the_readme_is_short_and_shows_at_least_three_figures():
  assert len(README.splitlines()) <= MAX_LINES
  figures = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", README)
  assert len(figures) >= 3, figures


def test_every_file_the_readme_shows_or_links_exists():
  targets = [target.split("#")[0] for target in re.findall(r"\]\(([^)]+)\)", README)
             if not re.match(r"https?://", target)]
  missing = [target for target in targets if target and not (ROOT / target).exists()]
  assert not missing, missing
