"""Output paths we may replace: a bag directory or a generated file is overwritten (``--force``) only when it is
ours, and a bag is replaced atomically (written beside it, then renamed into place).

Rules (issue 25: ``--force`` used to ``rmtree`` any folder):

* a **bag directory** is ours when everything in it is a rosbag2 file (``metadata.yaml``, ``*.mcap``, ``*.db3``
  and sqlite's ``-wal``/``-shm``/``-journal`` files); an empty directory is ours too.  Anything else (a
  ``notes.txt``, a sub-folder) makes :func:`check_bag_target` refuse it, naming what it found;
* an existing **file** where a bag directory should go is refused: ``--force`` replaces bag directories only;
* a **generated file** (a model or truth YAML, a URDF from a DH table) is replaced only when its first lines
  hold the marker we write (:func:`check_generated_file`).

:class:`BagReplacement` writes the new bag into ``<parent>/.<name>.ppoe-new-<random>/<name>`` and, on
:meth:`~BagReplacement.commit`, renames the old bag aside, the new one into place, and removes the old; on
:meth:`~BagReplacement.discard` (an error, or a recording that got nothing) the old bag stays untouched.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

from ppoe_core.errors import BagError, PpoeError

__all__ = ["BAG_FILE_SUFFIXES", "BagReplacement", "check_bag_target", "check_generated_file", "foreign_entries"]

#: names a rosbag2 directory holds (rosbags and ros2 bag, mcap and sqlite3 storage)
BAG_FILE_SUFFIXES = (".mcap", ".db3", ".db3-wal", ".db3-shm", ".db3-journal")
BAG_FILE_NAMES = ("metadata.yaml", "metadata.yaml.tmp")
#: at most this many foreign entries are named in a message
NAMED_AT_MOST = 5
#: a generated file carries its marker in one of its first this many lines
MARKER_LINES = 3


def foreign_entries(directory: Path) -> list[str]:
    """Entries of ``directory`` that are not rosbag2 files (sub-folders end in ``/``), sorted."""
    out = []
    for entry in sorted(directory.iterdir()):
        if entry.is_dir() and not entry.is_symlink():
            out.append(entry.name + "/")
        elif not (entry.name in BAG_FILE_NAMES or entry.name.endswith(BAG_FILE_SUFFIXES)) or entry.is_symlink():
            out.append(entry.name)
    return out


def _named(entries: Sequence[str]) -> str:
    shown = ", ".join(entries[:NAMED_AT_MOST])
    return shown + (f" and {len(entries) - NAMED_AT_MOST} more" if len(entries) > NAMED_AT_MOST else "")


def check_bag_target(path: Path, overwrite: bool, option: str = "--force") -> bool:
    """Whether writing a bag at ``path`` replaces an existing bag (True) or creates a new one (False).

    Raises
    ------
    BagError
        ``path`` exists and ``overwrite`` is False; ``path`` is a file (or a link); ``path`` is a directory that
        holds anything but rosbag2 files (named).
    """
    if not path.exists() and not path.is_symlink():
        return False
    if path.is_symlink() or not path.is_dir():
        raise BagError(f"bag {path}: is an existing file, not a bag directory; {option} replaces only a bag "
                       "directory (choose another output path)")
    if not overwrite:
        raise BagError(f"bag {path} exists already (pass overwrite=True / {option})")
    foreign = foreign_entries(path)
    if foreign:
        raise BagError(f"bag {path}: {option} refused: the folder holds {len(foreign)} entr"
                       f"{'y' if len(foreign) == 1 else 'ies'} that are not part of a bag ({_named(foreign)}); "
                       "it replaces only a folder holding a bag (move them, or choose another output path)")
    return True


def check_generated_file(path: Path, overwrite: bool, header: str, what: str, option: str = "--force") -> None:
    """Refuse to write ``path`` over a file that exists (without ``overwrite``) or that we did not write (none of
    its first :data:`MARKER_LINES` lines holds ``header``).

    Raises
    ------
    PpoeError
        Naming the file and the reason.
    """
    if not path.exists() and not path.is_symlink():
        return
    if path.is_dir() or path.is_symlink():
        raise PpoeError(f"{what} {path}: is an existing {'folder' if path.is_dir() else 'link'}; choose another path")
    if not overwrite:
        raise PpoeError(f"{what} {path} exists already (pass {option} to replace it)")
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            first = [f.readline() for _ in range(MARKER_LINES)]
    except OSError as exc:
        raise PpoeError(f"{what} {path}: cannot read it ({exc.strerror or exc})") from None
    if not any(header in line for line in first):
        raise PpoeError(f"{what} {path}: {option} refused: the file was not written by ppoe (its first lines do not "
                        f"hold '{header.strip()}'); choose another path")


class BagReplacement:
    """A new bag written beside an existing one of ours, then renamed into its place.

    Parameters
    ----------
    target : Path
        The existing bag directory (checked by :func:`check_bag_target`).

    Attributes
    ----------
    write_path : Path
        Where to write the new bag: ``<parent>/.<name>.ppoe-new-<random>/<name>``.
    """

    def __init__(self, target: Path) -> None:
        self.target = target
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.ppoe-new-", dir=target.parent))
        except OSError as exc:
            raise BagError(f"bag {target}: cannot create a folder beside it to write the new bag into "
                           f"({exc.strerror or exc})") from None
        self.write_path = self._tmp / target.name

    def commit(self) -> None:
        """Swap: the old bag aside, the new one into place, then the old one removed (re-checked to be a bag)."""
        old = self._tmp / (self.target.name + ".old")
        foreign = foreign_entries(self.target) if self.target.is_dir() else []
        if foreign:
            raise BagError(f"bag {self.target}: while writing, {_named(foreign)} appeared in it; the new bag is "
                           f"left in {self.write_path}")
        try:
            if self.target.exists():
                self.target.rename(old)
            self.write_path.rename(self.target)
        except OSError as exc:
            raise BagError(f"bag {self.target}: cannot move the new bag into place ({exc.strerror or exc}); it is in "
                           f"{self.write_path}") from None
        shutil.rmtree(self._tmp, ignore_errors=True)

    def discard(self) -> None:
        """Remove the new bag; the old one stays as it was."""
        shutil.rmtree(self._tmp, ignore_errors=True)
