"""pycolmap's import leaves the process's failure signals as Python had them."""

import subprocess
import sys

PROBE = """
import signal
def caught():
  status = dict(line.split(":", 1) for line in open("/proc/self/status"))
  mask = int(status["SigCgt"], 16)
  return {signal.Signals(n).name for n in range(1, 32) if mask >> (n - 1) & 1}
before = caught()
import {module}
print(sorted(caught() - before))
"""


def _newly_caught_signals(module: str) -> str:
  result = subprocess.run([sys.executable, "-c", PROBE.replace("{module}", module)],
                          capture_output=True, text=True, check=True, timeout=120)
  return result.stdout.strip()


def test_pycolmap_alone_installs_failure_handlers_and_our_import_takes_them_back():
  # The control: without the project's import, glog catches the failure signals; a fault in
  # its handler's stack unwinding then hangs the process (the test suite's worker did).
  assert "SIGSEGV" in _newly_caught_signals("pycolmap")
  assert _newly_caught_signals("signerf_jax.data.structure_from_motion") == "[]"
