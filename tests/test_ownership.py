"""The project touches only what it wrote (`signerf_jax.ownership`): claims refuse what is not
theirs, writes are recorded and never replace a user's file, deletions follow the record, a
killed write's temporary file is removed by its recorded name, one process holds a directory."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from signerf_jax import directory_lock, files, ownership
from signerf_jax.errors import InputError

# Files a user keeps beside the project's: dot-files, names like the project's temporary files
# (".<stem>.<8 characters>.<suffix>") and folders named like its stages.
USER_FILES = (".env.database", ".profile.original", "notes/deep/.vimrc.template",
              "notes/.htaccess.previous", "notes/.tool.settings.json",
              "selection/my_selection.json", "reference/paper.pdf", ".sheet.a1b2c3d4.png")


def write_user_files(directory: Path) -> dict[Path, bytes]:
  contents = {}
  for index, name in enumerate(USER_FILES):
    path = directory / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(f"user file {index}".encode())
    contents[path] = path.read_bytes()
  return contents


def assert_unchanged(contents: dict[Path, bytes]) -> None:
  for path, data in contents.items():
    assert path.is_file() and path.read_bytes() == data, path


def test_a_new_directory_is_marked_and_an_empty_one_taken(tmp_path):
  with ownership.claimed(tmp_path / "new", ownership.RUN):
    files.write_text(tmp_path / "new" / "model.json", "{}")
  assert ownership.owner_root(tmp_path / "new" / "model.json") == (tmp_path / "new").resolve()
  assert ownership.owner_kind((tmp_path / "new").resolve()) == ownership.RUN
  (tmp_path / "empty").mkdir()
  with ownership.claimed(tmp_path / "empty", ownership.DATASET):
    pass
  assert ownership.owner_kind((tmp_path / "empty").resolve()) == ownership.DATASET


def test_a_directory_of_other_files_is_refused_untouched(tmp_path):
  capture = tmp_path / "capture"
  contents = write_user_files(capture)
  with pytest.raises(InputError, match=r"holds files signerf did not write \(\.env\.database, "
                     r"\.profile\.original, \.sheet\.a1b2c3d4\.png and 3 more\)") as error:
    with ownership.claimed(capture, ownership.DATASET):
      pytest.fail("claimed")
  assert error.value.field == "out"
  assert not (capture / ownership.MARKER_FOLDER).exists()
  assert_unchanged(contents)


def test_another_kind_of_signerf_directory_is_refused(tmp_path):
  with ownership.claimed(tmp_path / "edit", ownership.EDIT):
    pass
  with pytest.raises(InputError, match="is a signerf edit directory, not a run directory"):
    ownership.check_claimable(tmp_path / "edit", ownership.RUN)
  # A directory inside a claimed one belongs to it, whatever it holds (an edit's original run).
  ownership.check_claimable(tmp_path / "edit" / "original", ownership.RUN)


@pytest.mark.parametrize("output, relation", [
    ("scene", "is"), ("scene/run", "lies inside"), (".", "holds")])
def test_an_output_that_overlaps_an_input_is_refused(tmp_path, output, relation):
  scene = tmp_path / "scene"
  scene.mkdir()
  with pytest.raises(InputError, match=f"{relation} the input given as --data"):
    ownership.check_claimable(tmp_path / output, ownership.RUN, inputs=(("data", scene),))


def test_a_users_file_is_never_replaced_nor_deleted(tmp_path):
  edit = tmp_path / "edit"
  with ownership.claimed(edit, ownership.EDIT):
    files.write_text(edit / "selection" / "selection.json", "{}")
    files.write_text(edit / "config.gin", "a = 1\n")
    contents = write_user_files(edit)
    with pytest.raises(InputError, match="was not written by signerf") as error:
      files.write_text(edit / "reference" / "paper.pdf", "overwritten")
    assert error.value.path == str(edit / "reference" / "paper.pdf")
    with pytest.raises(InputError, match="was not written by signerf"):
      ownership.remove_file(edit / "notes" / ".tool.settings.json")
    files.write_text(edit / "config.gin", "a = 2\n")  # The project's own: replaced.
    assert ownership.remove_written(edit / "selection") == 1
    assert ownership.remove_written(edit) == 1
  assert not (edit / "selection" / "selection.json").exists()
  assert not (edit / "config.gin").exists()
  assert_unchanged(contents)
  assert (edit / "selection").is_dir()  # It holds the user's my_selection.json.


def test_remove_written_drops_the_emptied_folders_it_made(tmp_path):
  with ownership.claimed(tmp_path / "run", ownership.RUN):
    files.write_text(tmp_path / "run" / "eval" / "deep" / "a.png", "x")
    (tmp_path / "run" / "mine").mkdir()  # The user's empty folder stays.
    ownership.remove_written(tmp_path / "run" / "eval")
  assert not (tmp_path / "run" / "eval").exists()
  assert (tmp_path / "run" / "mine").is_dir()


def test_a_killed_writes_temporary_file_is_removed_by_its_recorded_name(tmp_path):
  run = tmp_path / "run"
  script = textwrap.dedent(f"""
      import os, sys
      from signerf_jax import directory_lock, files, ownership
      with ownership.claimed({str(run)!r}, ownership.RUN):
        with files.atomic_path({str(run / "checkpoint.msgpack")!r}) as temporary:
          temporary.write_bytes(b"half written")
          print(temporary.name, flush=True)
          os.kill(os.getpid(), 9)
  """)
  process = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                           timeout=60, check=False)
  assert process.returncode == -signal.SIGKILL
  leftover = run / process.stdout.strip()
  assert leftover.is_file()
  look_alike = run / ".checkpoint.0badc0de.msgpack"  # The user's, however it looks.
  look_alike.write_bytes(b"user")
  with ownership.claimed(run, ownership.RUN):
    pass
  assert not leftover.exists()
  assert look_alike.read_bytes() == b"user"
  assert not (run / "checkpoint.msgpack").exists()


def test_a_file_the_user_put_where_the_project_had_one_is_the_users(tmp_path):
  run = tmp_path / "run"
  with ownership.claimed(run, ownership.RUN):
    files.write_text(run / "eval.json", "{}")
  (run / "eval.json").unlink()
  with ownership.claimed(run, ownership.RUN):  # The record forgets the removed file.
    pass
  (run / "eval.json").write_text("the user's")
  with ownership.claimed(run, ownership.RUN):
    with pytest.raises(InputError, match="was not written by signerf"):
      files.write_text(run / "eval.json", "{}")
  assert (run / "eval.json").read_text() == "the user's"


def test_a_symbolic_link_out_of_the_directory_is_not_followed_for_a_write(tmp_path):
  outside = tmp_path / "outside"
  outside.mkdir()
  with ownership.claimed(tmp_path / "edit", ownership.EDIT):
    (tmp_path / "edit" / "sheet").symlink_to(outside)
    with pytest.raises(InputError, match="leads outside the output directory"):
      files.write_text(tmp_path / "edit" / "sheet" / "sheet.png", "x")
  assert not any(outside.iterdir())


def test_a_full_disk_names_the_file_and_keeps_the_old_one(tmp_path, monkeypatch):
  target = tmp_path / "run" / "checkpoint.msgpack"
  with ownership.claimed(tmp_path / "run", ownership.RUN):
    files.write_bytes(target, b"previous")

    def full(*args):
      raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)  # As a write() on a full disk fails.
    with pytest.raises(InputError, match="could not be written: No space left on device") as error:
      files.write_bytes(target, b"next")
  assert error.value.path == str(target)
  assert target.read_bytes() == b"previous"
  assert [path.name for path in target.parent.iterdir()] == [ownership.MARKER_FOLDER,
                                                                target.name]


def test_claims_nest_within_a_process(tmp_path):
  with ownership.claimed(tmp_path / "edit", ownership.EDIT):
    with ownership.claimed(tmp_path / "edit" / "original", ownership.RUN):
      files.write_text(tmp_path / "edit" / "original" / "model.json", "{}")
    files.write_text(tmp_path / "edit" / "stages.json", "{}")  # Still claimed.
    assert ownership.remove_written(tmp_path / "edit") == 2
  assert not (tmp_path / "edit" / "original" / ownership.MARKER_FOLDER).exists()


def join_claim(edit: Path) -> subprocess.CompletedProcess:
  """A child process that joins the claim on `edit` and writes original/model.json there, then
  tries to replace the user's reference/paper.pdf (it prints the error)."""
  script = textwrap.dedent(f"""
      from pathlib import Path
      from signerf_jax import files, ownership
      from signerf_jax.errors import InputError
      edit = Path({str(edit)!r})
      with ownership.joined(edit):
        files.write_text(edit / "original" / "model.json", "{{}}")
        try:
          files.write_text(edit / "reference" / "paper.pdf", "overwritten")
        except InputError as error:
          print(error)
  """)
  return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                        timeout=60)


def test_a_child_that_joins_the_claim_writes_under_it_and_the_parent_reads_that_back(tmp_path):
  edit = tmp_path / "edit"
  with ownership.claimed(edit, ownership.EDIT):
    contents = write_user_files(edit)
    child = join_claim(edit)
    assert child.returncode == 0, child.stderr
    assert "paper.pdf: exists and was not written by signerf" in child.stdout
    ownership.refresh(edit)
    assert ownership.written_files(edit) == [edit / "original" / "model.json"]
    assert ownership.remove_written(edit) == 1
  assert_unchanged(contents)
  # Once the claim is released, no process may join it.
  child = join_claim(edit)
  assert child.returncode != 0
  assert "edit: is not claimed by this process's parent" in child.stderr
  assert not (edit / "original" / "model.json").exists()


def hold_claim(directory: Path) -> subprocess.Popen:
  """A process that claims `directory` and waits (it prints "held" once it holds the lock)."""
  script = textwrap.dedent(f"""
      import time
      from signerf_jax import ownership
      with ownership.claimed({str(directory)!r}, ownership.RUN):
        print("held", flush=True)
        time.sleep(120)
  """)
  process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
  assert process.stdout.readline().strip() == "held"
  return process


def test_one_process_per_directory_and_a_dead_holders_lock_is_taken_over(tmp_path):
  run = tmp_path / "run"
  holder = hold_claim(run)
  try:
    with pytest.raises(directory_lock.DirectoryInUse, match=f"in use by another signerf process "
                       rf"\(pid {holder.pid}\)"):
      ownership.check_claimable(run, ownership.RUN)
    with pytest.raises(directory_lock.DirectoryInUse, match=f"pid {holder.pid}"):
      with ownership.claimed(run / "eval", ownership.RUN):
        pytest.fail("claimed")
  finally:
    holder.kill()
    holder.wait(timeout=30)
  with ownership.claimed(run, ownership.RUN):
    lock = (run / ownership.MARKER_FOLDER / ownership.LOCK_FILE).read_text()
  assert lock.strip() == str(os.getpid())


def test_the_record_survives_a_record_cut_short(tmp_path):
  run = tmp_path / "run"
  with ownership.claimed(run, ownership.RUN):
    files.write_text(run / "model.json", "{}")
  with open(run / ownership.MARKER_FOLDER / ownership.LOG_FILE, "a") as log:
    log.write('["w", "half')  # A kill in the middle of an append.
  with ownership.claimed(run, ownership.RUN):
    files.write_text(run / "model.json", "{}")
  records = (run / ownership.MARKER_FOLDER / ownership.LOG_FILE).read_text().splitlines()
  assert all(isinstance(json.loads(line), list) for line in records)


def test_the_record_is_compacted_when_claimed(tmp_path):
  """A claim's cost does not grow with the checkpoints a long run wrote: a thousand rewrites of
  one file leave one record."""
  run = tmp_path / "run"
  with ownership.claimed(run, ownership.RUN):
    for _ in range(1000):
      ownership.record_written(run / "checkpoint.msgpack")
    (run / "checkpoint.msgpack").write_bytes(b"x")
  with ownership.claimed(run, ownership.RUN):
    pass
  assert len((run / ownership.MARKER_FOLDER / ownership.LOG_FILE).read_text().splitlines()) == 1


@pytest.mark.parametrize("kind, flag", [(ownership.RUN, "run"), (ownership.EDIT, "edit"),
                                        (ownership.DATASET, "out"), (ownership.RENDERS, "out"),
                                        (ownership.DEMO, "out")])
def test_a_refusal_names_the_flag_the_commands_give_the_kind_by(tmp_path, kind, flag):
  write_user_files(tmp_path / "mine")
  with pytest.raises(InputError, match="holds files signerf did not write") as error:
    ownership.check_claimable(tmp_path / "mine", kind)
  assert error.value.field == flag
  with pytest.raises(InputError) as error:
    ownership.check_claimable(tmp_path / "mine", kind, flag="given")
  assert error.value.field == "given"
