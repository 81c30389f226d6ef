"""The operational data store on a real PostgreSQL server (started by the session fixture).

Same behaviour as the SQLite store (exactly once per (robot, seq), counts,
queries, export, migrations), plus what only a shared server has: two cloud
nodes inserting the same records at once, nodes migrating together, and a
server that goes away and comes back.  ~10 s.
"""

from __future__ import annotations

import json
import os
import pwd
import random
import subprocess
import sys
import threading

import pytest

from scmr_mesh.data.errors import StoreError
from scmr_mesh.data.ods import SCHEMA_VERSION, OperationalDataStore, is_dsn, migrations
from scmr_mesh.data.ods_pg import PostgresStore, redact
from scmr_mesh.data.record import make_record
from scmr_mesh.data.report import telemetry_report


def test_a_url_opens_the_postgres_store_with_the_same_schema(pg_dsn):
    assert is_dsn(pg_dsn) and not is_dsn("runs/ods.sqlite")
    with OperationalDataStore(pg_dsn) as ods:
        assert isinstance(ods, PostgresStore) and ods.backend == "postgresql"
        assert ods.schema_version() == SCHEMA_VERSION
        cols = [c for (c,) in ods._read("SELECT column_name FROM information_schema.columns "
                                        "WHERE table_name = 'telemetry' ORDER BY ordinal_position")]
        assert cols == ["id", "robot", "inc", "seq", "t_unix_ns", "x", "y", "theta", "battery", "health",
                        "results", "received_from", "stored_unix_ns", "digest"]
        # doubles, not PostgreSQL's 4-byte REAL; 64-bit times
        types = dict(ods._read("SELECT column_name, data_type FROM information_schema.columns "
                               "WHERE table_name = 'telemetry'"))
        assert types["x"] == "double precision" and types["t_unix_ns"] == "bigint"
    assert len(migrations("postgresql")) == SCHEMA_VERSION


def test_exactly_once_counts_queries_and_export_match_sqlite(pg_dsn, tmp_path):
    recs = [make_record(f"r{r}", s, pose=(r, s + 0.123456789, 0.5), battery=1 - s / 10,
                        results={"frames": s}, t_unix_ns=1000 * s + r) for r in (1, 2) for s in (1, 2, 3, 5)]
    batches = [recs[:5], recs[3:], recs[:2] + [make_record("r1", 2, t_unix_ns=7)]]  # replays + a conflict
    out = {}
    for name, target in (("pg", pg_dsn), ("sqlite", tmp_path / "ods.sqlite")):
        with OperationalDataStore(target) as ods:
            results = [ods.insert(b, received_from="cloud") for b in batches]
            out[name] = {
                "results": [(r.stored, r.duplicates, r.contiguous, r.conflicts) for r in results],
                "counts": ods.counts(), "seqs": ods.seqs("r2"), "latest": ods.latest(),
                "range": ods.range(since_ns=2000, until_ns=3002),
                "report": telemetry_report(ods, {"r1": 6, "r2": 5})["telemetry"],
            }
            ods.export(tmp_path / f"{name}.json", fmt="json")
            out[name]["export"] = [{k: v for k, v in row.items() if k != "stored_unix_ns"}
                                   for row in json.loads((tmp_path / f"{name}.json").read_text())]
    for key in ("latest", "range"):
        for rows in (out["pg"][key], out["sqlite"][key]):
            for row in (rows.values() if isinstance(rows, dict) else rows):
                row.pop("stored_unix_ns")
    assert out["pg"] == out["sqlite"]
    assert out["pg"]["counts"]["r1"] == {"stored": 4, "duplicates": 3, "conflicts": 1, "min_seq": 1,
                                         "max_seq": 5, "contiguous": 3, "inc": 0, "incarnations": 1,
                                         "stored_all": 4}
    assert out["pg"]["latest"]["r1"]["pose"] == [1.0, 5.123456789, 0.5]  # float8 round trip


def test_two_cloud_nodes_storing_the_same_records_at_once_store_each_once(pg_dsn):
    """Two stores (two connections, as two cloud nodes) insert every pair, shuffled, concurrently."""
    pairs = [(f"r{i}", s) for i in range(4) for s in range(1, 151)]
    rng = random.Random(11)
    plans = []
    for _ in range(2):
        p = pairs[:]
        rng.shuffle(p)
        plans.append([p[i:i + 16] for i in range(0, len(p), 16)])
    a, b = OperationalDataStore(pg_dsn), OperationalDataStore(pg_dsn)
    errors, acks = [], []
    start = threading.Barrier(4)

    def run(ods, batches):
        try:
            start.wait()
            for bt in batches:
                acks.append(ods.insert([make_record(r, s, t_unix_ns=s) for r, s in bt], received_from="cloud"))
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(ods, plan[k::2]))
               for ods, plan in ((a, plans[0]), (b, plans[1])) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        assert not errors
        counts = a.counts()
        for i in range(4):
            c = counts[f"r{i}"]
            assert a.seqs(f"r{i}") == list(range(1, 151))
            assert c["stored"] == 150 and c["duplicates"] == 150 and c["conflicts"] == 0
            assert c["contiguous"] == 150  # the acknowledgement never went backwards or stalled
        assert sum(len(r.stored) for r in acks) == 600 and sum(len(r.duplicates) for r in acks) == 600
    finally:
        a.close()
        b.close()


def test_cloud_nodes_opening_a_new_database_together_migrate_once(pg_dsn):
    code = ("import sys; from scmr_mesh.data.ods import OperationalDataStore as O; "
            "o = O(sys.argv[1]); print(o.schema_version()); o.close()")
    procs = [subprocess.Popen([sys.executable, "-c", code, pg_dsn], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for _ in range(3)]
    outs = [p.communicate(timeout=60) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], outs
    assert [o.strip() for o, _ in outs] == [str(SCHEMA_VERSION)] * 3
    with OperationalDataStore(pg_dsn, readonly=True) as ods:
        assert ods._read("SELECT count(*) FROM ods_version") == [(1,)]
        assert ods._read("SELECT count(*) FROM meta") == [(1,)]  # migration 2 ran once


def test_read_only_needs_an_ods_and_errors_are_one_line(pg_server, pg_dsn):
    with pytest.raises(StoreError, match="holds no operational data store yet"):
        OperationalDataStore(pg_dsn, readonly=True)
    bad = pg_dsn.rsplit("?", 1)[0].replace("/t", "/nosuchdb_t", 1) + "?" + pg_dsn.rsplit("?", 1)[1]
    with pytest.raises(StoreError) as ei:
        OperationalDataStore(bad)
    msg = str(ei.value)
    assert "unreachable" in msg and "nosuchdb" in msg and "\n" not in msg and "start the PostgreSQL server" in msg
    assert redact("postgresql://u:secret@h:5/db") == "postgresql://u:***@h:5/db"


def test_a_server_that_goes_away_fails_inserts_then_serves_again(tmp_path):
    """Inserts while the server is stopped fail with one line (nothing half-stored); then resume."""
    from scmr_mesh.fleet.pgserver import PgServer

    pg = PgServer(tmp_path / "pg")
    dsn = pg.start()
    try:
        ods = OperationalDataStore(dsn)
        ods.insert([make_record("r1", 1, t_unix_ns=1)], received_from="cloud")
        pg.stop()
        for _ in range(2):  # the broken connection, then a refused reconnect
            with pytest.raises(StoreError, match="unreachable") as ei:
                ods.insert([make_record("r1", 2, t_unix_ns=2)], received_from="cloud")
            assert "\n" not in str(ei.value)
        pg.start()
        import time

        end = time.monotonic() + 10
        while True:
            try:
                res = ods.insert([make_record("r1", 2, t_unix_ns=2), make_record("r1", 3, t_unix_ns=3)],
                                 received_from="cloud")
                break
            except StoreError:
                assert time.monotonic() < end
                time.sleep(0.1)
        assert res.contiguous == {"r1": 3} and ods.counts()["r1"]["stored"] == 3
        ods.close()
    finally:
        pg.remove()


def test_scmr_ods_commands_read_a_postgres_store(pg_dsn):
    with OperationalDataStore(pg_dsn) as ods:
        ods.insert([make_record("r7", s, t_unix_ns=s) for s in (1, 2, 3)], received_from="cloud")
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "ods", "--db", pg_dsn, "counts", "--json"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["r7"]["stored"] == 3


def test_scmr_ods_reads_a_run_folders_postgres_cluster_stopped_or_running(tmp_path, capsys):
    """`scmr up --clouds 3` leaves RUN/postgres stopped; `scmr ods --db RUN` starts it for the query."""
    from scmr_mesh.cli import main
    from scmr_mesh.fleet.pgserver import PgServer

    import shutil
    import tempfile
    from pathlib import Path

    run = Path(tempfile.mkdtemp(prefix="scmr-odsrun-"))  # a folder PostgreSQL's user can enter (pytest's is 0700)
    run.chmod(0o711)
    pg = PgServer(run / "postgres")  # where the fleet runner puts it
    assert pg.root == (run / "postgres").resolve()
    with OperationalDataStore(pg.start()) as ods:
        ods.insert([make_record("r1", s) for s in (1, 2, 3)] + [make_record("r2", 1)], received_from="cloud")
    pg.stop()
    pidfile = run / "postgres" / "pgdata" / "postmaster.pid"
    assert not pidfile.exists()
    try:
        assert main(["ods", "--db", str(run), "counts", "--json"]) == 0
        out = capsys.readouterr()
        assert {r: c["stored"] for r, c in json.loads(out.out).items()} == {"r1": 3, "r2": 1}
        assert "started the run's PostgreSQL server" in out.err
        assert not pidfile.exists()  # stopped again
        # while the run's server runs, its socket is used and the server is left running
        pg.start()
        assert main(["ods", "--db", str(run), "counts", "--json"]) == 0
        out = capsys.readouterr()
        assert json.loads(out.out)["r1"]["stored"] == 3 and "started" not in out.err
        assert pg.alive()
        pg.stop()
        # several queries at once on the stopped cluster: serialised, none stops a server another reads
        cmd = [sys.executable, "-m", "scmr_mesh", "ods", "--db", str(run), "counts", "--json"]
        procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(4)]
        outs = [p.communicate(timeout=120) for p in procs]
        assert [p.returncode for p in procs] == [0] * 4, [o[1] for o in outs]
        assert all(json.loads(o[0])["r1"]["stored"] == 3 for o in outs)
        assert not pidfile.exists()
        # a stopped cluster that belongs to another user is not started (root would hand it to postgres)
        if os.geteuid() == 0:
            nobody = pwd.getpwnam("nobody")
            os.chown(run / "postgres" / "pgdata", nobody.pw_uid, nobody.pw_gid)
            assert main(["ods", "--db", str(run), "counts"]) == 1
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "belongs to user 'nobody'" in err[0] and "as root or as nobody" in err[0], err
            os.chown(run / "postgres" / "pgdata", pwd.getpwnam(pg.user).pw_uid, -1)
    finally:
        pg.remove()
        shutil.rmtree(run, ignore_errors=True)


def test_scmr_ods_on_a_folder_without_a_store_says_so(tmp_path, capsys):
    from scmr_mesh.cli import main

    assert main(["ods", "--db", str(tmp_path), "counts"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no data store" in err[0] and "postgresql://" in err[0], err


@pytest.mark.parametrize("store, says", [
    ("postgresql://scmr@/scmr?host=/tmp/scmr-pg-x1/socket&port=5432", "was outside the run folder"),
    ("postgresql://scmr@db.site:5432/scmr", "used the postgresql store postgresql://scmr@db.site:5432/scmr; pass it"),
])
def test_scmr_ods_on_a_run_whose_postgres_store_is_elsewhere(tmp_path, capsys, store, says):
    from scmr_mesh.cli import main

    (tmp_path / "report.json").write_text(json.dumps({"ods": {"backend": "postgresql", "store": store}}))
    assert main(["ods", "--db", str(tmp_path), "counts"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err


def test_scmr_ods_on_a_run_folder_follows_its_report(tmp_path, capsys):
    """A run that used a SQLite file elsewhere (`scmr up --ods FILE`) says where."""
    from scmr_mesh.cli import main

    (tmp_path / "report.json").write_text(json.dumps({"ods": {"backend": "sqlite", "store": "/data/x.sqlite"}}))
    assert main(["ods", "--db", str(tmp_path), "counts"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "used the sqlite store /data/x.sqlite; pass it with --db" in err[0], err


def test_a_version_3_database_migrates_to_incarnations_keeping_its_rows(pg_dsn):
    """Schema v4 (issue 25 item 10) rebuilds the telemetry table keyed by (robot, inc, seq) on PostgreSQL
    too: the old rows keep incarnation 0, new ids do not collide with them, and a replay of an old
    record is still a duplicate."""
    import psycopg

    from scmr_mesh.data.record import make_record

    with psycopg.connect(pg_dsn, autocommit=True) as con:
        con.execute("CREATE TABLE ods_version (version INTEGER NOT NULL)")
        con.execute("INSERT INTO ods_version (version) VALUES (3)")
        for step in migrations("postgresql")[:3]:
            for stmt in step:
                con.execute(stmt)
        con.execute("INSERT INTO telemetry (robot, seq, t_unix_ns, health, results, received_from, stored_unix_ns) "
                    "VALUES ('r1', 1, 5, 'ok', '{}', 'cloud', 6)")
        con.execute("INSERT INTO robot_stats (robot, duplicates, contiguous) VALUES ('r1', 0, 1)")
    with OperationalDataStore(pg_dsn) as ods:
        res = ods.insert([make_record("r1", 1, t_unix_ns=5), make_record("r1", 2, t_unix_ns=6)], received_from="cloud")
        assert res.duplicates == (("r1", 1),) and res.stored == (("r1", 2),) and not res.conflicts
        assert ods.schema_version() == SCHEMA_VERSION == 4 and ods.incarnations("r1") == {0: 2}
        assert ods.counts()["r1"]["contiguous"] == 2
