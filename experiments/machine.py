"""The machine a benchmark ran on, recorded beside its numbers."""

from __future__ import annotations

import os
import platform
from typing import Any

import jax


def record(**extra: Any) -> dict[str, Any]:
  """Platform, CPUs, JAX version, `extra` fields and the 1/5/15-minute load averages now (call it
  when the measurement starts)."""
  return {"platform": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
          **extra, "load_average_at_start": os.getloadavg()}
