"""``scmr energy``: the Eq 4.9 table, experiment 7's sweep, one placement explained.

Sizes and rates accept units.  Plain numbers are bytes and bytes/s (SI);
suffixes follow the thesis's binary convention: ``kB`` = 1024 B, ``MB`` =
1048576 B (Eq 4.9's "1 MB"), ``kB/s``, ``MB/s``, and ``Mb/s`` = 131072 B/s
(Eq 4.9: 23 Mb/s = 3014656 B/s).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

from scmr_mesh import cliargs as ca
from scmr_mesh.errors import InputError

_SIZE_UNITS = {"": 1, "b": 1, "kb": 1024, "kib": 1024, "mb": 1048576, "mib": 1048576, "gb": 1 << 30, "gib": 1 << 30}
#: Accepted rate units (case-sensitive: "MB/s" is bytes, "Mb/s" the thesis's 2**20 bit/s).
_RATE_UNITS = {"": 1.0, "B/s": 1.0, "kB/s": 1024.0, "KB/s": 1024.0, "MB/s": 1048576.0, "Mb/s": 131072.0, "Mbps": 131072.0}
_NUM = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([A-Za-z/]*)\s*$")

DEFAULT_SIZES = "0.5MB,1MB,2MB,3MB,4MB"
DEFAULT_BANDWIDTHS = ",".join(f"{b}Mb/s" for b in range(5, 101, 5))


def parse_size(text: str) -> int:
    """``"1MB"`` -> 1048576; plain numbers are bytes."""
    m = _NUM.match(text)
    unit = m.group(2).lower() if m else None
    if not m or unit not in _SIZE_UNITS:
        raise InputError(f"size must be a number with an optional unit B, kB, MB, GB (binary), got {text!r}")
    value = float(m.group(1)) * _SIZE_UNITS[unit]
    if not math.isfinite(value):
        raise InputError(f"size must be finite, got {text!r}")
    return int(round(value))


def parse_rate(text: str) -> float:
    """``"23Mb/s"`` -> 3014656.0; plain numbers are bytes/s."""
    m = _NUM.match(text)
    if not m:
        raise InputError(f"rate must be a number with an optional unit B/s, kB/s, MB/s or Mb/s, got {text!r}")
    raw_unit = m.group(2)
    if raw_unit not in _RATE_UNITS:
        raise InputError(
            f"rate unit {raw_unit!r} not understood in {text!r}; use B/s, kB/s, MB/s (bytes) or Mb/s (2**20 bit/s)"
        )
    factor = _RATE_UNITS[raw_unit]
    value = float(m.group(1)) * factor
    if not math.isfinite(value) or value <= 0:
        raise InputError(f"rate must be a finite number > 0, got {text!r}")
    return value


def _list(text: str, parse) -> list:
    items = [t for t in text.split(",") if t.strip()]
    if not items:
        raise InputError(f"expected a comma-separated list, got {text!r}")
    return [parse(t) for t in items]


def _positive_float(name: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"{name} must be a number, got {text!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a finite number > 0, got {text!r}")
    return v


def _write_json(path: str | None, doc: Any) -> None:
    if not path:
        return
    try:
        Path(path).write_text(json.dumps(doc, indent=2, default=_json_default) + "\n")
    except OSError as exc:
        raise InputError(f"cannot write JSON to {path!r} ({exc.strerror}); give a writable path") from None
    print(f"wrote {path}", file=sys.stderr)


def _json_default(o: Any) -> Any:
    if isinstance(o, frozenset):
        return sorted(o)
    raise TypeError(type(o).__name__)


def _finite(x: float) -> Any:
    return x if math.isfinite(x) else None


def _profiles(args: argparse.Namespace, names: str | None):
    from scmr_mesh.energy.profiles import all_profiles, get_profile

    if not names:
        return list(all_profiles(profiles_file=args.profiles_file).values())
    return [get_profile(n.strip(), profiles_file=args.profiles_file) for n in names.split(",") if n.strip()]


# ---------------------------------------------------------------- handlers


def _cmd_table(args: argparse.Namespace) -> int:
    from scmr_mesh.energy.experiments import eq49_table

    result = eq49_table(_profiles(args, args.profile))
    print("Eq 4.9: C = 5e9 cycles, D = 1 MiB up and down, B_u = 3014656 B/s (23 Mb/s), "
          "B_d = 3670016 B/s (28 Mb/s), F = 300 (inputs assumed: thesis values)")
    head = f"{'profile':<10} {'E_proc J':>10} {'E_idle J':>10} {'E_trans J':>10} {'E_cloud J':>10} {'E_saved J':>10}  decision"
    print(head)
    print("-" * len(head))
    for r in result["rows"]:
        print(
            f"{r['profile']:<10} {r['e_proc_j']:>10.3f} {r['e_idle_j']:>10.4f} {r['e_trans_j']:>10.3f} "
            f"{r['e_cloud_j']:>10.3f} {r['e_saved_j']:>10.3f}  {r['decision']}"
        )
    _write_json(args.json, result)
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from scmr_mesh.energy.experiments import plot_sweep, sweep
    from scmr_mesh.energy.model import MIB, THESIS_MBPS

    sizes = _list(args.sizes, parse_size)
    bws = _list(args.bandwidths, parse_rate)
    if any(s <= 0 for s in sizes):
        raise InputError(f"--sizes must all be > 0 bytes, got {args.sizes!r}")
    cycles = _positive_float("--cycles", args.cycles)
    ratio = _positive_float("--down-up-ratio", args.down_up_ratio)
    reply = parse_size(args.reply_bytes) if args.reply_bytes is not None else None
    profs = _profiles(args, args.profile)
    print(f"sweeping {len(profs)} profile(s) x {len(sizes)} size(s) x {len(bws)} bandwidth(s)", file=sys.stderr)
    result = sweep(
        profs,
        sizes_bytes=sizes,
        bandwidths_Bps=sorted(bws),
        cycles=cycles,
        reply_bytes=reply,
        down_up_ratio=ratio,
        cloud_factor=_positive_float("--cloud-factor", args.cloud_factor),
    )
    print(f"break-even upload bandwidth (Mb/s = 131072 B/s; B_d = {ratio:g} x B_u; "
          f"reply = {'same as upload' if reply is None else f'{reply} B'}; C = {cycles:g} cycles)")
    print(f"{'profile':<10} " + " ".join(f"{s / MIB:>9g}MB" for s in sizes))
    for pr in result["profiles"]:
        cells = []
        for b in pr["break_even"]:
            v = b["closed_form_Bps"]
            cells.append(f"{v / THESIS_MBPS:>11.2f}" if math.isfinite(v) else f"{'never':>11}")
        print(f"{pr['profile']:<10} " + " ".join(cells))
    for pr in result["profiles"]:
        for b in pr["break_even"]:
            for k in ("closed_form_Bps", "numeric_Bps", "closed_form_mbps"):
                b[k] = _finite(b[k])
    _write_json(args.json, result)
    if args.plot:
        plot_sweep(result, args.plot)
        print(f"wrote {args.plot}", file=sys.stderr)
    return 0


def _cmd_place(args: argparse.Namespace) -> int:
    from scmr_mesh.energy.measure import cycles_from_cpu_time, host_clock_hz
    from scmr_mesh.energy.placement import LinkEstimate, Task, choose_placement
    from scmr_mesh.energy.profiles import get_profile

    profile = get_profile(args.profile, profiles_file=args.profiles_file)
    measured: set[str] = set()
    if (args.cycles is None) == (args.cpu_seconds is None):
        raise InputError("give exactly one of --cycles C or --cpu-seconds S (CPU time measured on this host)")
    if args.cycles is not None:
        cycles = _positive_float("--cycles", args.cycles)
        host_note = None
    else:
        hz, host_note = host_clock_hz()
        cycles = cycles_from_cpu_time(_positive_float("--cpu-seconds", args.cpu_seconds), hz)
        measured.add("cycles")
    deadline = _positive_float("--deadline", args.deadline) if args.deadline is not None else None
    task = Task(cycles, parse_size(args.up), parse_size(args.down), deadline, measured=frozenset(measured))
    up = parse_rate(args.bandwidth_up)
    down = parse_rate(args.bandwidth_down) if args.bandwidth_down else up
    try:
        rtt = float(args.rtt)
    except ValueError:
        raise InputError(f"--rtt must be a number of seconds >= 0, got {args.rtt!r}") from None
    if not math.isfinite(rtt) or rtt < 0:
        raise InputError(f"--rtt must be a number of seconds >= 0, got {args.rtt!r}")
    links = {"cloud": LinkEstimate(up, down, rtt)}
    lup = parse_rate(args.leader_bandwidth_up) if args.leader_bandwidth_up else up
    ldown = parse_rate(args.leader_bandwidth_down) if args.leader_bandwidth_down else down
    links["leader"] = LinkEstimate(lup, ldown, rtt, _positive_float("--leader-hz", args.leader_hz) if args.leader_hz else None)
    reachable = [t.strip() for t in args.reachable.split(",") if t.strip() and t.strip() != "none"]
    placement = choose_placement(
        task, profile, reachable=reachable, links=links, dvs=args.dvs,
        cloud_factor=_positive_float("--cloud-factor", args.cloud_factor),
    )
    print(f"decision: {placement.tier}" + ("  (DEADLINE MISSED)" if placement.deadline_missed else ""))
    print(f"why: {placement.reason}")
    print(f"{'option':<8} {'robot J':>12} {'time s':>10}  meets deadline")
    for o in placement.options:
        extra = f"  at {o['clock_hz'] / 1e9:.3g} GHz (DVS)" if o.get("dvs") else ""
        print(f"{o['tier']:<8} {o['robot_energy_j']:>12.4f} {o['predicted_s']:>10.4f}  {o['meets_deadline']}{extra}")
    print("inputs:")
    for k, v in placement.inputs.items():
        print(f"  {k:<18} {v['value']!s:>16} {v['unit']:<10} {v['source']}")
    if host_note:
        print(f"  (host clock {host_note})")
    _write_json(args.json, placement.to_dict())
    return 0


def _cmd_profiles(args: argparse.Namespace) -> int:
    from scmr_mesh.energy.profiles import all_profiles

    profs = all_profiles(profiles_file=args.profiles_file)
    print(f"{'name':<12} {'P_c W':>8} {'P_i W':>8} {'P_u W':>8} {'P_d W':>8} {'clock GHz':>10}  source")
    for p in profs.values():
        print(
            f"{p.name:<12} {p.p_compute_w:>8.2f} {p.p_idle_w:>8.2f} {p.p_up_w:>8.2f} {p.p_down_w:>8.2f} "
            f"{p.clock_hz / 1e9:>10.3f}  {p.source}"
        )
    _write_json(args.json, {"profiles": [p.to_dict() for p in profs.values()]})
    return 0


def _frame_files(data: str) -> list[Path]:
    root = Path(data)
    manifest = root / "manifest.json"
    if manifest.is_file():
        try:
            items = json.loads(manifest.read_text())["items"]
            files = [root / it["image"] for it in items]
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(f"{manifest}: not a roads manifest ({exc}); pass a folder of PNG/JPEG frames") from None
    elif root.is_dir():
        files = sorted(p for p in root.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    else:
        raise InputError(f"--data {data} is not a folder; pass the roads folder (with manifest.json) or PNG/JPEG frames")
    files = [f for f in files if f.is_file()]
    if not files:
        raise InputError(f"--data {data} holds no PNG/JPEG frame")
    return files


# ---------------------------------------------------------------- parsers


def _common(p: argparse.ArgumentParser, *, json_help: str) -> None:
    p.add_argument("--profiles-file", type=ca.PathArg("in-file", what="a TOML file of energy profiles"), metavar="TOML", help="user profiles (schemas/energy-profiles.schema.json); "
                   "they add to, or replace, the built-in Table 4.3 profiles")
    p.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help=json_help)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scmr energy {table,sweep,place,profiles}``."""
    # the module docstring's examples close the help of `scmr energy` and its subcommands
    examples = {"epilog": __doc__.split("\n\n", 1)[1], "formatter_class": argparse.RawDescriptionHelpFormatter}
    energy = sub.add_parser(
        "energy",
        help="energy model: Eq 4.9 table, experiment 7 sweep, placement decisions",
        description=(
            "The robot energy model of thesis 4.3 in SI units: E_proc = P_c*C/S_r (local), "
            "E_cloud = P_i*C/S_c + P_u*D_up/B_u + P_d*D_down/B_d (offloaded, S_c = F*S_r), "
            "E_saved = E_proc - E_cloud.  See docs/ENERGY.md."
        ),
        **examples,
    )
    esub = energy.add_subparsers(dest="energy_command", metavar="SUBCOMMAND")
    energy.set_defaults(func=lambda args: (energy.print_help(sys.stderr), 2)[1])

    t = esub.add_parser(
        "table",
        help="the thesis's Eq 4.9 worked example for every Table 4.3 profile",
        description=(
            "Eq 4.9 worked example (C = 5e9 cycles, D = 1 MiB up and down, B_u = 3014656 B/s, "
            "B_d = 3670016 B/s, F = 300) for each profile: E_proc, E_idle, E_trans, E_cloud, "
            "E_saved and the decision (offload when E_saved > 0)."
        ),
    )
    t.add_argument("--profile", metavar="NAMES", help="comma-separated profile names (default: all)")
    _common(t, json_help='write {"rows": [{"profile", "e_proc_j", ...}]} to FILE')
    t.set_defaults(func=_cmd_table)

    s = esub.add_parser(
        "sweep",
        help="experiment 7: energy saved over image size x bandwidth, break-even per size",
        description=(
            "E_saved over image size x upload bandwidth for each profile, with the break-even "
            "bandwidth per size in closed form, cross-checked by bisection."
        ),
        **examples,
    )
    s.add_argument("--sizes", type=ca.parsed(lambda t: _list(t, parse_size), what="sizes such as 0.5MB,1MB", example="1MB,3MB", keep_text=True), default=DEFAULT_SIZES, help=f"upload sizes (default {DEFAULT_SIZES})")
    s.add_argument("--bandwidths", type=ca.parsed(lambda t: _list(t, parse_rate), what="rates such as 10Mb/s,20Mb/s", example="10Mb/s,20Mb/s", keep_text=True), default=DEFAULT_BANDWIDTHS, help="upload bandwidths (default 5..100 Mb/s step 5)")
    s.add_argument("--profile", metavar="NAMES", help="comma-separated profile names (default: all)")
    s.add_argument("--cycles", type=ca.positive("cycles", example="5e9"), default="5e9", help="C, cycles per task (default 5e9, the thesis's C = 5)")
    s.add_argument("--reply-bytes", type=ca.parsed(parse_size, what="a size such as 1MB", example="1MB", keep_text=True), metavar="SIZE", help="D_down (default: same as the upload size, as the thesis)")
    s.add_argument("--down-up-ratio", type=ca.positive("", example="1.2"), default="1", help="B_d / B_u (default 1; Eq 4.9 uses 28/23)")
    s.add_argument("--cloud-factor", type=ca.positive("", example="300"), default="300", help="F in S_c = F * S_r (default 300)")
    s.add_argument("--plot", type=ca.PathArg("out-file"), metavar="PNG", help="draw E_saved vs bandwidth per profile to PNG (OpenCV)")
    _common(s, json_help="write the grid and break-even bandwidths to FILE")
    s.set_defaults(func=_cmd_sweep)

    p = esub.add_parser(
        "place",
        help="explain one placement decision (local, cloud or leader)",
        description=(
            "Evaluate local execution and every reachable remote tier for one task and explain the "
            "choice: least robot energy among options meeting --deadline; if none meets it, the "
            "fastest, flagged as a deadline miss."
        ),
        **examples,
    )
    p.add_argument("--profile", required=True, help="robot profile name (leader, robot1..robot4 or from --profiles-file)")
    p.add_argument("--cycles", type=ca.positive("cycles", example="5e9"), help="C, cycles the task needs (assumed input)")
    p.add_argument("--cpu-seconds", type=ca.positive("seconds", example="0.004"), help="instead of --cycles: CPU time measured on this host (C = s x host clock)")
    p.add_argument("--up", type=ca.parsed(parse_size, what="a size such as 1MB", example="1MB", positive=False, keep_text=True), required=True, help="request bytes D_up (e.g. 1MB, 250000)")
    p.add_argument("--down", type=ca.parsed(parse_size, what="a size such as 1MB", example="1MB", positive=False, keep_text=True), required=True, help="reply bytes D_down")
    p.add_argument("--bandwidth-up", type=ca.parsed(parse_rate, what="a rate such as 23Mb/s", example="23Mb/s", keep_text=True), required=True, help="upload rate to the cloud (e.g. 23Mb/s, 3014656)")
    p.add_argument("--bandwidth-down", type=ca.parsed(parse_rate, what="a rate such as 28Mb/s", example="28Mb/s", keep_text=True), help="download rate (default: same as up)")
    p.add_argument("--leader-bandwidth-up", type=ca.parsed(parse_rate, what="a rate such as 23Mb/s", example="23Mb/s", keep_text=True), help="upload rate to the leader (default: the cloud's)")
    p.add_argument("--leader-bandwidth-down", type=ca.parsed(parse_rate, what="a rate such as 28Mb/s", example="28Mb/s", keep_text=True), help="download rate from the leader (default: the cloud's)")
    p.add_argument("--leader-hz", type=ca.positive("Hz", example="3.5e9"), help="the leader's clock in Hz (default: leader profile, 3.5e9)")
    p.add_argument("--rtt", default="0", type=ca.non_negative("seconds", example="0.01"), help="round-trip time added to remote requests, s (default 0)")
    p.add_argument("--deadline", type=ca.positive("seconds", example="2"), help="delay deadline T, s (default: none)")
    p.add_argument("--reachable", default="cloud,leader", help="reachable remote tiers, comma-separated, or 'none'")
    p.add_argument("--dvs", action="store_true", help="run local execution at the lowest DVS clock that meets T")
    p.add_argument("--cloud-factor", type=ca.positive("", example="300"), default="300", help="F in S_c = F * S_r (default 300)")
    _common(p, json_help="write the placement (options and inputs marked measured/assumed) to FILE")
    p.set_defaults(func=_cmd_place)

    pr = esub.add_parser(
        "profiles",
        help="list profiles (built-in Table 4.3 and --profiles-file), validating the file",
        description="List the built-in profiles and those of --profiles-file (validated against the schema).",
    )
    _common(pr, json_help="write the profiles to FILE")
    pr.set_defaults(func=_cmd_profiles)
