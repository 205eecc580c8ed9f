"""``--out DIR`` of ``ppoe evaluate`` / ``ppoe diagnose``: checked and created before the run, not after it."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ppoe_core.errors import PpoeError

__all__ = ["prepare_out_dir"]


def prepare_out_dir(out: str | os.PathLike, option: str = "--out") -> Path:
    """Create ``out`` (with parents) and check that files can be written there.

    Raises
    ------
    PpoeError
        ``out`` is an existing file, cannot be created, or is not writable; the message names it.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise PpoeError(f"{option} {path}: is an existing file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".ppoe_write_check_"):
            pass
    except OSError as exc:
        raise PpoeError(f"{option} {path}: cannot write there ({exc.strerror or exc})") from None
    return path
