"""The `signerf` entry point's process-wide settings, and how it ends an interrupted command."""

from __future__ import annotations

import signal
import sys
import types

import jax
import pytest

from signerf_jax import allocator, cli, training_loop


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
  assert cli.main(["train", "--data", str(tmp_path / "missing"), "--run",
                   str(tmp_path / "run")]) == 2
  assert calls == [True]
  assert cli.main(["preview", "--run", str(tmp_path / "missing"), "--edit",
                   str(tmp_path / "edit")]) == 2
  assert calls == [True]  # The diffusion sampler runs slower keeping freed memory.
  # An edit's commands train in a child process that keeps it (editing.commands.training_process).
  for command in (["edit", "--edit", "E"], ["demo"], ["finetune", "--edit", "E"],
                  ["eval", "--edit", "E"], ["preview", "--edit", "E"]):
    assert not cli.keeps_freed_memory(cli.build_parser(command).parse_args(command)), command
  for command in (["eval", "--run", "R"], ["render", "--run", "R"], ["view", "--run", "R"]):
    assert cli.keeps_freed_memory(cli.build_parser(command).parse_args(command)), command


@pytest.fixture
def fake_command(monkeypatch):
  """`signerf train` and `signerf render` run `fake.run` (set by the test) instead."""
  fake = types.ModuleType("fake_signerf_command")
  fake.add_arguments = lambda parser: None
  monkeypatch.setitem(sys.modules, fake.__name__, fake)
  for name in ("train", "render"):
    monkeypatch.setitem(cli.COMMANDS, name, (fake.__name__, "a fake command"))
  monkeypatch.setattr(allocator, "keep_freed_memory", lambda: None)
  monkeypatch.setattr(cli, "use_compilation_cache", lambda: None)
  return fake


def test_an_interrupted_training_run_reports_its_step_and_checkpoint_in_one_line(fake_command,
                                                                                capsys):
  def run(args):
    raise training_loop.TrainingInterrupted(1234, signal.SIGINT, "runs/lego", saved=True)

  fake_command.run = run
  assert cli.main(["train"]) == 130
  assert capsys.readouterr().err == ("signerf train: interrupted at step 1234; checkpoint saved "
                                     "in runs/lego; run the same command to resume\n")


def test_sigterm_during_a_training_loop_checkpoints_and_exits_with_143(fake_command, capsys,
                                                                      tmp_path):
  saved, handlers = [], []

  def advance(seconds):
    handlers.append(signal.getsignal(signal.SIGTERM))
    if len(handlers) == 3:
      signal.raise_signal(signal.SIGTERM)  # The step still completes.
    return {"loss": 1.0}

  fake_command.run = lambda args: training_loop.run_loop(
      advance, saved.append, training_loop.LoopBudget(until_step=100), step=0,
      where=tmp_path / "run", progress=False)
  assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
  assert cli.main(["train"]) == 143
  assert len(saved) == 1 and len(handlers) == 3
  assert capsys.readouterr().err == (f"signerf train: interrupted at step 3; checkpoint saved in "
                                     f"{tmp_path / 'run'}; run the same command to resume\n")
  assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # Only for the command's duration.


@pytest.mark.parametrize("command,signum,expected", [
    ("train", signal.SIGINT, "signerf train: interrupted; run the same command to resume\n"),
    ("train", signal.SIGTERM, "signerf train: interrupted; run the same command to resume\n"),
    ("render", signal.SIGINT, "signerf render: interrupted\n"),
])
def test_a_signal_outside_training_ends_the_command_in_one_line(fake_command, capsys, command,
                                                                signum, expected):
  def run(args):
    signal.raise_signal(signum)  # Ctrl-C raises KeyboardInterrupt, SIGTERM Terminated.
    raise AssertionError("not stopped by the signal")

  fake_command.run = run
  assert cli.main([command]) == 128 + signum
  assert capsys.readouterr().err == expected
