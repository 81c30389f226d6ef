"""``scmr scenario run|check|plan|cleanup``: scripted fault scenarios (issue 4).

Heavy modules (the runner, OpenCV, the proxies) are imported inside the
handlers so ``scmr --help`` stays fast.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from scmr_mesh import cliargs as ca
from scmr_mesh.errors import ConfigError, ScenarioError, ScmrError

DESCRIPTION = """\
Scripted fault scenarios against a fleet on one host (thesis chapter 4).

A scenario file (TOML; schema in schemas/scenario.schema.json; examples in
peers/scenarios/) declares the fleet, its links, a timeline of faults
(link_down, partition, crash, bandwidth, latency, loss) and expectations.

  scmr scenario check peers/scenarios/*.toml            validate files
  scmr scenario plan peers/scenarios/cloud-link-drop.toml   the exact ip/tc commands
  scmr scenario run peers/scenarios/cloud-link-drop.toml    run it, write a report
  scmr scenario cleanup                                 remove leftovers of a crashed run
"""


def _out(msg: str) -> None:
    print(msg, flush=True)


def _err(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _cmd_check(args: argparse.Namespace) -> int:
    from scmr_mesh.scenario.spec import load_scenario

    bad = 0
    for f in args.files:
        try:
            sc = load_scenario(f)
        except ConfigError as exc:
            if len(args.files) == 1:
                raise
            _err(f"scmr: error: {exc}")
            bad += 1
            continue
        _out(f"{f}: ok - {sc.name}: {len(sc.robots)} robots, {len(sc.links)} links, "
             f"{len(sc.faults)} faults, {len(sc.expectations)} expectations, {sc.duration_s:g} s, seed {sc.seed}")
    return 1 if bad else 0


def _fmt_cmd(c) -> str:
    return c if isinstance(c, str) else " ".join(c)


def _cmd_plan(args: argparse.Namespace) -> int:
    from scmr_mesh.scenario.plan import NetnsLayout, compile_timeline, proxy_actions
    from scmr_mesh.scenario.spec import load_scenario

    sc = load_scenario(args.file)
    events = compile_timeline(sc)
    if args.backend == "netns":
        layout = NetnsLayout(sc, run_id=args.run_id)
        for when, action in layout.plan(events):
            w = when if isinstance(when, str) else f"t={when:g}s"
            _out(f"{w:>9}  {_fmt_cmd(action)}")
        if sc.shape == "routers":  # who runs where (the processes are started by `scenario run`)
            for p in sc.peer_names:
                rep = f"tcp/{layout.addr(p)}:{layout.port + 1}"
                dials = ", ".join(sc.router_dials(p)) or "nobody"
                _out(f"{'hosts':>9}  {layout.ns(p)}: router {sc.router_of(p)} on {rep} dials {dials}; "
                     f"{p} is its client")
    elif sc.shape == "routers":
        raise ScenarioError(f"scenario {sc.name}: topology.shape = \"routers\" has no proxy plan; "
                            "use --backend netns (scmr scenario plan FILE --backend netns)")
    else:
        _out(f"    setup  one TCP proxy per link: {', '.join(a + '->' + b for a, b in sc.links)}; gossip off")
        for e in events:
            if e.op in ("kill", "start"):
                _out(f"{'t=' + format(e.at_s, 'g') + 's':>9}  {e.op} {e.target[0]}")
            for link, action, value in proxy_actions(sc.links, e):
                v = (" unlimited" if action == "rate" else "") if value is None else f" {value}"
                _out(f"{'t=' + format(e.at_s, 'g') + 's':>9}  proxy {link[0]}->{link[1]}: {action}{v}")
        _out(" teardown  close every proxy")
    return 0


def _cmd_cleanup(args: argparse.Namespace) -> int:
    from scmr_mesh.scenario.netns import check_root, cleanup_stale

    check_root()
    removed = cleanup_stale()
    _out(f"removed {len(removed)} namespace(s)" + (": " + ", ".join(removed) if removed else ""))
    return 0


def _with_overrides(sc, args: argparse.Namespace):
    """Apply --process / --lease-ms / --duration overrides (recorded in the report's notes)."""
    import dataclasses

    changes = {}
    if getattr(args, "process", None):
        changes["process"] = args.process
    if getattr(args, "lease_ms", None):
        if args.lease_ms < 10:
            raise ConfigError(f"--lease-ms must be at least 10, got {args.lease_ms}")
        changes["lease_ms"] = args.lease_ms
    if getattr(args, "shape", None):
        changes["shape"] = args.shape
    return dataclasses.replace(sc, **changes) if changes else sc


def _auto_backend(backend: str) -> str:
    if backend == "auto":
        backend = "netns" if hasattr(os, "geteuid") and os.geteuid() == 0 else "proxy"
        _err(f"scenario: backend {backend} ({'root' if backend == 'netns' else 'not root'}; choose with --backend)")
    return backend


def _cmd_run(args: argparse.Namespace) -> int:
    from scmr_mesh.scenario.report import run_report, write_report
    from scmr_mesh.scenario.runner import run_scenario
    from scmr_mesh.scenario.spec import load_scenario

    sc = _with_overrides(load_scenario(args.file), args)
    backend = _auto_backend(args.backend)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    out = Path(args.out) if args.out else Path("runs") / f"scenario-{sc.name}-{stamp}"
    from scmr_mesh.viz import RerunOptions, peers_env_session

    # rerun (--save/--spawn/--serve/--connect): robots in network namespaces cannot reach the
    # host's loopback, so there each saves its own file, merged in at the end (docs/VIEWER.md)
    rerun_dir = out / "rerun" if backend == "netns" else None
    with peers_env_session(RerunOptions.from_args(args), robots=[r.id for r in sc.robots],
                           save_dir=rerun_dir) as fviz:
        res = run_scenario(sc, backend=backend, out_dir=out, data_dir=args.data,
                           progress=lambda m: _err(f"scenario: {m}"), ready_timeout=args.ready_timeout,
                           insecure=args.insecure)
        if fviz is not None:
            if res.t0_unix_ns:  # the faults plot spans the run (docs/VIEWER.md)
                fviz.set_run_span(res.t0_unix_ns, res.t0_unix_ns + int(sc.duration_s * 1e9))
            fviz.update(records=sorted(res.records, key=lambda r: r.get("received_unix_ns") or 0),
                        faults=res.metric_faults())
    if fviz is not None and fviz.saved_path is not None:
        _err(f"scenario: rerun recording {fviz.saved_path} (open it with `scmr view {fviz.saved_path}`)")
    if fviz is not None and fviz.peers_path is not None:
        _err(f"scenario: the robots ran in network namespaces and could not stream live; their "
             f"recording is {fviz.peers_path} (open it with `scmr view {fviz.peers_path}`)")
    thesis = Path(args.thesis_csv) if args.thesis_csv else None
    if thesis is None:
        from scmr_mesh.scenario.runner import default_data_dir

        cand = default_data_dir().parent / "thesis_table_4_2.csv"
        thesis = cand if cand.is_file() else None
    report = run_report(res, thesis_csv=thesis)
    paths = write_report(report, out, json_path=Path(args.json) if args.json else None)
    s = report["summary"]
    _out(f"{sc.name} ({backend}): {s['requests']} requests, RoR {s['ror'] if s['ror'] is None else round(s['ror'], 3)}, "
         f"ToR p50 {s['tor_ms']['p50'] and round(s['tor_ms']['p50'], 1)} ms p99 "
         f"{s['tor_ms']['p99'] and round(s['tor_ms']['p99'], 1)} ms, tiers {s['by_tier']}")
    for f in report["faults"]:
        line = f"  fault {f['label']}: "
        if f.get("tier") is not None or not (f.get("reroute_ms") or f.get("no_path")):
            line += f"failover gap {f['failover_gap_ms']} ms" + (
                "" if f.get("ended_at_s") is None else f", failback gap {f['failback_gap_ms']} ms")
        if f.get("reroute_ms") or f.get("no_path"):
            line += ("; " if f.get("tier") is not None else "") + "reroute " + ", ".join(
                f"{r} {'never' if v is None else f'{v:.0f} ms'}" for r, v in f["reroute_ms"].items())
            if f.get("no_path"):
                line += f"; no path to any server: {', '.join(f['no_path'])}"
        _out(line)
    mh = report.get("multihop") or {}
    if mh.get("max_hops") is not None and mh["max_hops"] > 1:
        _out(f"  multi-hop: up to {mh['max_hops']} radio hops; {mh['alone_with_path']} frames computed alone "
             f"with a path to a server; longest reroute {mh['max_reroute_ms']} ms; "
             f"longest split lead {mh['split_leader_ms']} ms")
    from scmr_mesh.fleet.output import format_leadership, format_telemetry

    _out("  " + format_telemetry(report.get("telemetry")))
    for line in format_leadership(report.get("leadership")):
        _out(line)
    for e in report["expectations"]:
        _out(f"  expectation {e['name']}: observed {e['observed']} -> {'held' if e['held'] else 'FAILED'}")
    for n in report["notes"]:
        _out(f"  note: {n}")
    for p in report["problems"]:
        _out(f"  PROBLEM: {p}")
    _out(f"report: {paths['md']} and {paths['json']} (plots {paths['tor_png'].name}, {paths['tiers_png'].name})")
    if not s["requests"]:
        raise ScmrError(f"scenario {sc.name}: no request was recorded; see the peer logs in {out / 'logs'}")
    return 0 if report["passed"] and not report["problems"] else 1


def _override_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--process", metavar="MODULE:FUNC", help="override the scenario's process function "
                   "(e.g. scmr_mesh.mesh.testing:stub_process to measure the network failover without the pipeline)")
    p.add_argument("--lease-ms", type=ca.count("milliseconds", lo=10, hi=3600000, example="500"), metavar="MS", help="override the scenario's zenoh lease")
    p.add_argument("--shape", choices=("clique", "routers"), default=None,
                   help="override the scenario's topology.shape: run the same scenario on the clique (peers, one "
                        "hop) or on routers (a router on every host, several hops) to compare them (docs/R2R.md)")
    p.add_argument("--insecure", action="store_true",
                   help="run the peers without authentication (default: a development CA and one certificate "
                        "per peer in OUT/certs, valid for every address peers listen on; mutual TLS and the "
                        "fleet's access rules on every link)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scmr scenario ...``."""
    p = sub.add_parser("scenario", help="scripted link-drop / crash / partition scenarios with reports",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    ssub = p.add_subparsers(dest="scenario_command", metavar="ACTION")
    p.set_defaults(func=lambda a: (p.print_help(sys.stderr), 2)[1])

    run = ssub.add_parser("run", help="run a scenario and write Markdown + JSON + PNG reports",
                          description="Run a scenario file against real peers, play its faults, write "
                          "report.md, report.json, tor.png and tiers.png. Exit 1 when an expectation fails.")
    run.add_argument("file", type=ca.PathArg("in-file", what="a scenario TOML file", example="peers/scenarios/cloud-crash.toml"), help="scenario TOML file (e.g. peers/scenarios/cloud-link-drop.toml)")
    run.add_argument("--backend", choices=["auto", "netns", "proxy", "loopback"], default="auto",
                     help="netns: a network namespace per peer, kernel-level faults (root); proxy: TCP proxies "
                          "per link on loopback (no root); loopback: direct endpoints on loopback, crashes only "
                          "(what scmr up runs on); auto (default): netns when root, else proxy")
    run.add_argument("--out", type=ca.PathArg("out-dir"), metavar="DIR", help="output folder (default runs/scenario-<name>-<UTC time>)")
    run.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the JSON report here (default DIR/report.json)")
    run.add_argument("--data", metavar="DIR", type=ca.PathArg("in-dir", as_path=True), default=None,
                     help="folder the image sets are relative to (default $SCMR_DATA or ../shared/data/roads)")
    run.add_argument("--thesis-csv", type=ca.PathArg("in-file"), metavar="FILE", help="thesis Table 4.2 CSV to compare with "
                     "(default: thesis_table_4_2.csv beside the data folder)")
    run.add_argument("--ready-timeout", type=ca.positive("seconds", hi=86400, example="120"), default=120.0, metavar="S",
                     help="seconds each peer may take to become ready (default 120)")
    _override_args(run)
    from scmr_mesh.viz import (
        add_rerun_args,  # light: rerun is imported only with a flag
    )

    add_rerun_args(run)
    run.set_defaults(func=_cmd_run)

    chk = ssub.add_parser("check", help="validate scenario files",
                          description="Validate scenario files against schemas/scenario.schema.json and the "
                          "rules of the scenario format; print a one-line summary of each.")
    chk.add_argument("files", type=ca.PathArg("in-file", what="a scenario TOML file", example="peers/scenarios/cloud-crash.toml"), nargs="+", help="scenario TOML files")
    chk.set_defaults(func=_cmd_check)

    pl = ssub.add_parser("plan", help="print the exact commands a scenario would issue (no root needed)",
                         description="Print the setup, fault and teardown actions of a scenario without "
                         "running anything: ip/tc commands for netns, proxy actions for proxy.")
    pl.add_argument("file", type=ca.PathArg("in-file", what="a scenario TOML file", example="peers/scenarios/cloud-crash.toml"), help="scenario TOML file")
    pl.add_argument("--backend", choices=["netns", "proxy"], default="netns", help="which backend's plan (default netns)")
    pl.add_argument("--run-id", default="RUNID", help="run id used in namespace names (default RUNID)")
    pl.set_defaults(func=_cmd_plan)

    cl = ssub.add_parser("cleanup", help="remove the project's network namespaces and their processes left by a killed run",
                         description="Kill the processes inside, and delete, every network namespace whose "
                         "name starts with one of the project's prefixes: 'scmrs-' (scenario runs), 'scmrm-' "
                         "(several-sites tests, the router probe), 'scmrb-' (the tx-stall bench), 'scmrh-' and 'scmrg-' "
                         "(the test suite's hosts). Only this project creates them; a run still going loses "
                         "its own, so run it when none is. Needs root.")
    cl.set_defaults(func=_cmd_cleanup)
