"""The machine a benchmark ran on, recorded beside its numbers."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

import jax


def cpu_model() -> str:
  """The CPU's model name, family and model number from /proc/cpuinfo ("" where there is none):
  the same platform string covers hosts whose speed differs by 2x (Zen 3 / 4 / 5)."""
  try:
    lines = Path("/proc/cpuinfo").read_text().splitlines()
  except OSError:
    return ""
  fields: dict[str, str] = {}
  for line in lines:
    key, _, value = line.partition(":")
    fields.setdefault(key.strip(), value.strip())
  return (f"{fields.get('model name', '?')}, CPU family {fields.get('cpu family', '?')} "
          f"model {fields.get('model', '?')}")


def record(**extra: Any) -> dict[str, Any]:
  """Platform, CPU model and count, JAX version, `extra` fields and the 1/5/15-minute load
  averages now (call it when the measurement starts)."""
  return {"platform": platform.platform(), "cpu": cpu_model(), "cpu_count": os.cpu_count(),
          "jax": jax.__version__, **extra, "load_average_at_start": os.getloadavg()}
