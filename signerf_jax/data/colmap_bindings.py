"""pycolmap, imported without the failure signal handlers it installs.

Importing pycolmap installs glog's failure handler for SIGSEGV, SIGABRT, SIGBUS, SIGILL, SIGFPE
and SIGTERM. It prints a stack trace by unwinding the stack, which takes the unwinder's lock;
when the failure itself happened inside the unwinder (as when LLVM aborted JAX's compiler, out
of memory maps, while an exception was being thrown) the process then hangs forever instead of
exiting. The dispositions Python had before the import are put back, and faulthandler, when it
was on, is turned on again.
"""

from __future__ import annotations

import faulthandler
import signal
import threading

FAILURE_SIGNALS = (signal.SIGSEGV, signal.SIGABRT, signal.SIGBUS, signal.SIGILL, signal.SIGFPE,
                   signal.SIGTERM)

_before = {number: signal.getsignal(number) for number in FAILURE_SIGNALS}
import pycolmap  # pylint: disable=g-import-not-at-top,wrong-import-position  (after _before)

# signal.signal works only in the main thread; an import elsewhere keeps glog's handlers.
if threading.current_thread() is threading.main_thread():
  for _number, _handler in _before.items():
    # None: a handler installed outside Python (faulthandler's, restored below).
    signal.signal(_number, signal.SIG_DFL if _handler is None else _handler)
  if faulthandler.is_enabled():
    faulthandler.enable()

__all__ = ["pycolmap", "FAILURE_SIGNALS"]
