"""The `signerf` entry point's process-wide settings."""

from __future__ import annotations

import jax
import pytest

from signerf_jax import allocator, cli


@pytest.fixture
def cache_settings():
  """Restores JAX's cache settings after a test changed them."""
  saved = (jax.config.jax_compilation_cache_dir,
           jax.config.jax_persistent_cache_min_compile_time_secs)
  yield
  jax.config.update("jax_compilation_cache_dir", saved[0])
  jax.config.update("jax_persistent_cache_min_compile_time_secs", saved[1])


def test_compiled_programs_are_kept_in_the_user_cache(cache_settings, monkeypatch, tmp_path):
  monkeypatch.delenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", raising=False)
  jax.config.update("jax_compilation_cache_dir", None)
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
  cli.use_compilation_cache()
  assert jax.config.jax_compilation_cache_dir == str(tmp_path / "signerf_jax" / "xla")
  assert jax.config.jax_persistent_cache_min_compile_time_secs == pytest.approx(0.1)


def test_a_cache_directory_chosen_for_jax_is_kept(cache_settings, monkeypatch, tmp_path):
  monkeypatch.delenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", raising=False)
  jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
  cli.use_compilation_cache()
  assert jax.config.jax_compilation_cache_dir == str(tmp_path / "mine")
  # The small programs are kept there too (JAX_COMPILATION_CACHE_DIR is how the benchmarks
  # give each run its own cache: they must measure what a user gets).
  assert jax.config.jax_persistent_cache_min_compile_time_secs == pytest.approx(0.1)


def test_a_threshold_chosen_for_jax_is_kept(cache_settings, monkeypatch):
  monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "2.5")
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 2.5)
  cli.use_compilation_cache()
  assert jax.config.jax_persistent_cache_min_compile_time_secs == pytest.approx(2.5)


def test_the_commands_that_train_a_nerf_keep_freed_memory(monkeypatch, tmp_path):
  calls = []
  monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(True))
  assert set(cli.KEEP_FREED_MEMORY_COMMANDS) <= set(cli.COMMANDS)
  # A missing dataset or run stops each command with an input error, after the allocator step.
  assert cli.main(["train", "--data", str(tmp_path / "missing"), "--out",
                   str(tmp_path / "run")]) == 2
  assert calls == [True]
  assert cli.main(["preview", "--run", str(tmp_path / "missing"), "--out",
                   str(tmp_path / "edit")]) == 2
  assert calls == [True]  # The diffusion sampler runs slower keeping freed memory.
