"""The dissertation's published figures shipped in the repo (``facts.toml``, ``table_4_2.csv``).

Every number of a claim in the ``scmr thesis`` report comes from here, with the section,
table or figure that prints it; tests/test_thesis.py checks each quote against the
dissertation's text and Table 4.2 against the shared CSV.
"""

from __future__ import annotations

import csv
import re
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
FACTS = HERE / "facts.toml"
TABLE_4_2 = HERE / "table_4_2.csv"


@dataclass(frozen=True)
class Fact:
    """One published figure or sentence: ``id``, where (``source``), the ``quote`` and its ``values``."""

    id: str
    source: str
    quote: str
    values: dict[str, float] = field(default_factory=dict)

    def claim(self, **extra: Any) -> dict[str, Any]:
        """The report's ``claim`` block for this fact."""
        return {"fact": self.id, "source": self.source, "quote": self.quote, "values": dict(self.values), **extra}


@lru_cache(maxsize=1)
def load_facts(path: Path = FACTS) -> dict[str, Fact]:
    """``{id: Fact}`` from ``facts.toml``."""
    doc = tomllib.loads(Path(path).read_text())
    return {k: Fact(k, v["source"], v["quote"], dict(v.get("values", {}))) for k, v in doc.items()}


def normalise(text: str) -> str:
    """Whitespace collapsed to single spaces (the text's tables use tabs, its equations double spaces)."""
    return re.sub(r"\s+", " ", text).strip()


@lru_cache(maxsize=1)
def table_4_2(path: Path = TABLE_4_2) -> list[dict[str, Any]]:
    """Table 4.2's rows (one per robot and image), numbers as ints, with the derived cloud ToR.

    ``cloud_tor_ms`` = download end - upload start (the request's whole time, as Eq 3.12).
    """
    rows = []
    with open(path, encoding="utf-8") as f:
        for r in csv.DictReader(f):
            row: dict[str, Any] = {}
            for k, v in r.items():
                row[k] = int(v) if v.lstrip("-").isdigit() else v
            row["robot_id"] = row["robot"].lower().replace(" ", "")
            row["cloud_tor_ms"] = row["download_end_ms"] - row["upload_start_ms"]
            rows.append(row)
    return rows


def table_4_2_for(robot_id: str) -> list[dict[str, Any]]:
    """The rows of one robot (``robot1`` ...), in the table's order."""
    return [r for r in table_4_2() if r["robot_id"] == robot_id]
