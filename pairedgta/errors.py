"""User-facing errors: one line that names the file or key and the fix."""
from __future__ import annotations

import errno
import os


class PairedGTAError(RuntimeError):
    """An error caused by input or configuration; printed as one line, exit code 2."""


class ConfigError(PairedGTAError):
    pass


class DataError(PairedGTAError):
    pass


class ModelError(PairedGTAError):
    pass


class RendererError(PairedGTAError):
    pass


class DiskFullError(PairedGTAError):
    """No space left (or the quota reached) while writing results."""


DISK_FULL = (errno.ENOSPC, errno.EDQUOT)  # no space left on device, disk quota exceeded


def disk_full(exc: BaseException, folder: str | os.PathLike) -> DiskFullError | None:
    """`exc` as the one line a full disk deserves (the folder being written, and the fix), or None when
    `exc` is something else. Writes go to temporary names that a failure removes, so nothing is half-written."""
    if not isinstance(exc, OSError) or exc.errno not in DISK_FULL:
        return None
    return DiskFullError(f"no space left on the disk of {folder} while writing it ({os.strerror(exc.errno)}); nothing "
                         "half-written was kept: free space there or set cache_dir=/another/disk, then rerun "
                         "(finished scenes and stages are kept)")


class WriteError(PairedGTAError):
    """Another failed write: a read-only file system, a file too large for it, an input/output error."""


WRITE_FAILED = (errno.EROFS, errno.EFBIG, errno.EIO)


def write_failed(exc: BaseException, folder: str | os.PathLike) -> PairedGTAError | None:
    """`disk_full(exc, folder)`, or for the other errors a write meets (`WRITE_FAILED`) the same one line with
    its cause and the file; None for anything else (a traceback: not a fault of the disk)."""
    full = disk_full(exc, folder)
    if full is not None or not isinstance(exc, OSError) or exc.errno not in WRITE_FAILED:
        return full
    where = f" ({exc.filename})" if exc.filename else ""
    return WriteError(f"{os.strerror(exc.errno).lower()}{where} while writing {folder}; nothing half-written was "
                      "kept: check that disk or set cache_dir=/another/disk, then rerun (finished scenes and stages "
                      "are kept)")


# boilerplate lines libraries put around the actual cause (torch's weights-only refusal)
_BOILERPLATE = (
    "Weights only load failed",
    "Check the documentation of torch.load",
    "Please file an issue with the following",
)


def reason(exc: BaseException) -> str:
    """The whole cause of `exc` on one line: type, then every informative line of its message (a refused
    pickle says which global it refused, e.g. ``GLOBAL posix.system``), never cut mid-reason."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    kept = [ln for ln in lines if not ln.startswith(_BOILERPLATE)] or lines
    text = " ".join(kept)
    if "WeightsUnpickler error:" in text:  # torch's refusal: the global it refused, not its advice to load anyway
        text = text.split("WeightsUnpickler error:", 1)[1].split(" Please use ", 1)[0].strip()
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class Terminated(BaseException):
    """SIGTERM turned into an exception, so cleanup runs as for Ctrl-C (not an Exception: nothing
    swallows it by accident)."""
