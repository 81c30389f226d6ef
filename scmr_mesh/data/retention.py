"""Bounded retention of the files a robot keeps (its masks): the newest N stay, older ones go.

A long run at 5 Hz writes 300 masks a minute per robot; without a bound a robot's folder grows
with the run (issue 25 item 11: 1.7 MB and 1,200 files a minute for 4 robots).  :class:`Retention`
keeps the newest ``keep`` files written through it, counting the ones already in the folder at
start (a restarted robot with the same ``--out``), oldest by sequence number first.
``keep=None`` keeps everything (``scmr robot --keep-all``).

Pure (file system only): no Zenoh.

Examples
--------
>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> r = Retention(d, keep=2)
>>> for seq in range(1, 5):
...     p = d / f"{seq}.mask.png"
...     _ = p.write_bytes(b"x")
...     r.add(p)
>>> sorted(p.name for p in d.iterdir()), r.deleted
(['3.mask.png', '4.mask.png'], 2)
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from pathlib import Path

log = logging.getLogger(__name__)

#: Masks a robot keeps in its inbox by default (about 3 minutes at 5 Hz, 1.5 MB of 1.4 KB masks).
DEFAULT_KEEP_MASKS = 1000
#: The masks' file names: ``<seq>.mask.png``.
MASK_SUFFIX = ".mask.png"


def _seq_of(path: Path, suffix: str) -> int | None:
    stem = path.name[: -len(suffix)] if path.name.endswith(suffix) else ""
    return int(stem) if stem.isdigit() else None


class Retention:
    """Keep the newest ``keep`` files named ``<seq><suffix>`` in ``folder``; delete older ones.

    Parameters
    ----------
    folder : path
        Where the files are (existing ones count, oldest seq first).
    keep : int or None
        How many to keep (>= 1); None keeps every file.
    suffix : str
        The files' suffix (default ``.mask.png``); other files are never touched.
    """

    def __init__(self, folder: str | Path, *, keep: int | None, suffix: str = MASK_SUFFIX) -> None:
        if keep is not None and keep < 1:
            raise ValueError(f"keep must be >= 1 or None (keep everything), got {keep}")
        self.folder = Path(folder)
        self.keep = keep
        self.suffix = suffix
        self.deleted = 0
        self._lock = threading.Lock()
        found = []
        if keep is not None and self.folder.is_dir():
            for p in self.folder.iterdir():
                seq = _seq_of(p, suffix)
                if seq is not None:
                    found.append((seq, p))
        self._files: deque[Path] = deque(p for _, p in sorted(found))
        self._trim()

    def add(self, path: str | Path) -> None:
        """A file was just written: remember it, delete the oldest beyond ``keep``."""
        if self.keep is None:
            return
        with self._lock:
            self._files.append(Path(path))
            self._trim()

    def __len__(self) -> int:
        return len(self._files)

    def _trim(self) -> None:
        while self.keep is not None and len(self._files) > self.keep:
            old = self._files.popleft()
            try:
                old.unlink()
                self.deleted += 1
            except FileNotFoundError:
                pass
            except OSError as exc:  # never stops the robot; the folder is just not trimmed
                log.warning("retention: cannot delete %s (%s)", old, exc)


__all__ = ["DEFAULT_KEEP_MASKS", "MASK_SUFFIX", "Retention"]
