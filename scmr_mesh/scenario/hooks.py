"""What a run tells the code around it (:class:`Hooks`), and reading robots' records as they are written.

``scmr up`` and ``scmr demo`` hang their live progress line, the rerun sink
and the run's PostgreSQL server on these hooks (``scmr_mesh.fleet.run``);
``scmr scenario run`` its progress messages (:class:`Say`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from scmr_mesh.scenario.runner import ScenarioRun

__all__ = ["Hooks", "RecordTail", "Say"]

log = logging.getLogger(__name__)


class Hooks:
    """What a run tells the code around it (all no-ops here; override what you need).

    ``scmr up`` and ``scmr demo`` hang their live progress line, the rerun
    sink and the run's PostgreSQL server on these; ``scmr scenario run`` its
    progress messages.  Each is called from the runner's (main) thread.
    """

    def setup(self, run: "ScenarioRun") -> None:
        """Before any peer starts (the run folder exists; ``run.options`` may still be replaced)."""

    def say(self, run: "ScenarioRun", message: str) -> None:
        """A one-line progress message."""

    def tick(self, run: "ScenarioRun") -> None:
        """About every 50 ms from time 0 until the robots finish (``run.records`` is up to date)."""

    def stopped(self, run: "ScenarioRun") -> None:
        """After every peer stopped and the backend was torn down (also after an error)."""

    def reported(self, result: Any, report: Mapping[str, Any]) -> None:
        """Once the run's report is built (``result``: the :class:`~scmr_mesh.scenario.runner.RunResult`).

        Called by whoever builds the report (``run_fleet``, ``scmr scenario run``): the
        demo draws its pictures here.
        """


class Say(Hooks):
    def __init__(self, progress: Callable[[str], None]) -> None:
        self.progress = progress

    def say(self, run: "ScenarioRun", message: str) -> None:
        self.progress(message)


class RecordTail:
    """Read the complete JSON lines appended to a ``records.jsonl`` since last time."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._pos = 0
        self._partial = b""
        self.bad_lines = 0

    def read_new(self) -> list[dict]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self._pos)
                data = f.read()
                self._pos = f.tell()
        except FileNotFoundError:
            return []
        data = self._partial + data
        lines = data.split(b"\n")
        self._partial = lines.pop()  # an incomplete last line waits for its end
        out = []
        for ln in lines:
            if not ln.strip():
                continue
            try:
                out.append(json.loads(ln))
            except json.JSONDecodeError:
                self.bad_lines += 1
                log.warning("%s: skipping a line that is not JSON: %.80r", self.path, ln)
        return out
