"""`scmr ods ...`: queries, exports, queue inspection and one-line errors."""

from __future__ import annotations

import json
from datetime import datetime, timezone

import pytest

from scmr_mesh.cli import main
from scmr_mesh.data.commands import parse_time_ns
from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.queue import TelemetryQueue
from scmr_mesh.data.record import make_record
from scmr_mesh.errors import InputError

T0 = 1_795_000_000 * 10**9


@pytest.fixture()
def db(tmp_path):
    path = tmp_path / "ods.sqlite"
    with OperationalDataStore(path) as ods:
        ods.insert([make_record(r, s, pose=(s, 0, 0), battery=0.9, t_unix_ns=T0 + s * 10**9)
                    for r in ("r1", "r2") for s in (1, 2, 3)], received_from="cloud")
        ods.insert([make_record("r1", 3, t_unix_ns=T0)], received_from="leader")
    return path


def test_counts_latest_range_export(db, tmp_path, capsys):
    assert main(["ods", "--db", str(db), "counts", "--json"]) == 0
    counts = json.loads(capsys.readouterr().out)
    assert counts["r1"] == {"stored": 3, "duplicates": 0, "conflicts": 1, "min_seq": 1, "max_seq": 3,
                            "contiguous": 3, "inc": 0, "incarnations": 1, "stored_all": 3}
    # r1 seq 3 sent again with another time: a conflict (no longer also counted as a duplicate)
    assert main(["ods", "--db", str(db), "counts"]) == 0
    assert "r2" in capsys.readouterr().out
    assert main(["ods", "--db", str(db), "latest", "--json"]) == 0
    assert {r: v["seq"] for r, v in json.loads(capsys.readouterr().out).items()} == {"r1": 3, "r2": 3}
    since = datetime.fromtimestamp((T0 + 2 * 10**9) / 1e9, tz=timezone.utc).isoformat()
    assert main(["ods", "--db", str(db), "range", "--since", since, "--until", str(T0 + 3 * 10**9),
                 "--robot", "r2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [json.loads(x)["seq"] for x in lines] == [2]
    out = tmp_path / "e.csv"
    assert main(["ods", "--db", str(db), "export", "--format", "csv", "--out", str(out)]) == 0
    assert len(out.read_text().splitlines()) == 1 + 6


def test_missing_and_corrupt_database_are_one_line_errors(tmp_path, capsys):
    assert main(["ods", "--db", str(tmp_path / "nope.sqlite"), "counts"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"scmr: error: --db {tmp_path / 'nope.sqlite'}: no such file") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"\x00garbage" * 512)
    assert main(["ods", "--db", str(bad), "latest"]) == 1
    assert "not a readable SQLite database" in capsys.readouterr().err


def test_bad_time_and_reversed_range(db, capsys):
    assert main(["ods", "--db", str(db), "range", "--since", "yesterday-ish"]) == 1
    assert "cannot read 'yesterday-ish' as a time" in capsys.readouterr().err
    assert main(["ods", "--db", str(db), "range", "--since", "20", "--until", "10"]) == 1
    assert "before --since" in capsys.readouterr().err


def test_parse_time_forms():
    assert parse_time_ns("1.5") == 1_500_000_000
    assert parse_time_ns(str(T0)) == T0
    assert parse_time_ns("1970-01-01T00:00:02Z") == 2 * 10**9
    assert parse_time_ns("1970-01-01T00:00:02") == 2 * 10**9
    with pytest.raises(InputError):
        parse_time_ns("soon")


def test_queue_inspection_reports_corruption(tmp_path, capsys):
    qdir = tmp_path / "q"
    with TelemetryQueue(qdir) as q:
        for _ in range(3):
            q.append(b"hello")
    assert main(["ods", "queue", str(qdir)]) == 0
    assert json.loads(capsys.readouterr().out)["depth"] == 3
    seg = next(qdir.glob("seg-*.log"))
    raw = bytearray(seg.read_bytes())
    raw[-1] ^= 0xFF  # last payload byte of seq 3
    seg.write_bytes(bytes(raw))
    assert main(["ods", "queue", str(qdir)]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out)["lost_seqs"] == [3]
    assert "1 seq(s) lost" in captured.err
    assert main(["ods", "queue", str(tmp_path / "none")]) == 1


def test_bench_data_reports_medians(tmp_path, capsys):
    out = tmp_path / "b.json"
    assert main(["bench", "data", "--n", "10", "--quiet", "--json", str(out)]) == 0
    res = json.loads(out.read_text())["results"]
    for k in ("queue_append_fsync_always", "ods_insert_batch64", "buffer_delta10_merge", "zenoh_store_ack_batch1"):
        assert res[k]["n"] == 10 and 0 < res[k]["median_ms"] <= res[k]["p99_ms"]
    drain = json.loads(out.read_text())["results"]["backlog_drain"]
    assert drain["stored"] == drain["backlog"] == 100 and drain["records_per_s"] > 0
    assert main(["bench", "data", "--n", "3"]) == 1
    assert "--n must be >= 10, got 3" in capsys.readouterr().err


def test_public_names_resolve_and_import_stays_light():
    import subprocess
    import sys

    import scmr_mesh.data as data

    for name in data.__all__:
        assert getattr(data, name).__name__ == name
    code = "import sys, scmr_mesh.data; print('sqlite3' in sys.modules, 'msgpack' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["False", "False"]


def test_queue_help_says_what_exit_1_means(capsys):
    """issue 25 item 2: the help and the exit status agree (lost seqs exit 1, and the help says so)."""
    assert main(["ods", "queue", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "exit 1 when it found a corrupt stretch or records lost to one" in text
