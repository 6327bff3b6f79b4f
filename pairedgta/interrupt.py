"""A stop request that survives code which swallows exceptions. Cycles renders inside Blender's Python
RenderEngine callback: a KeyboardInterrupt or Terminated raised there is printed by Blender and the
render goes on. The signal handlers record the request here as well as raising, and long loops (each
rendered image) call `check()`, which raises again once control is back in our code."""
from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

from pairedgta.errors import Terminated

_requested: list[int] = []
_deferring: list[bool] = []


def request(signum: int) -> bool:
    """Record a stop; True when the caller (a signal handler) should not raise now, because code that
    would swallow the exception is running (see `deferred`): `check()` raises it afterwards."""
    _requested.append(int(signum))
    return bool(_deferring)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Around a call into code that prints and swallows exceptions (a Cycles render, ~1 s): a signal
    arriving meanwhile is only recorded, and raised by `check()` right after."""
    _deferring.append(True)
    try:
        yield
    finally:
        _deferring.pop()
    check()


def clear() -> None:
    _requested.clear()


def check() -> None:
    """Raise the pending stop (KeyboardInterrupt for SIGINT, Terminated otherwise), if any."""
    if not _requested:
        return
    signum = _requested[0]
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(f"stopped by {signal.Signals(signum).name}")
