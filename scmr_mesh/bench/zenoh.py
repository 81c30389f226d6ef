"""``scmr bench zenoh PROBE``: the probes behind docs/ZENOH.md (:mod:`scmr_mesh.bench.probe`)."""

from __future__ import annotations

import json
import sys

from scmr_mesh.errors import InputError


def cmd_bench_zenoh(args) -> int:
    import contextlib
    import io

    from scmr_mesh.bench import probe

    rest = list(args.probe_args)
    json_path = args.json
    if "--json" in rest:  # also accepted after PROBE
        i = rest.index("--json")
        if i + 1 >= len(rest):
            raise InputError("--json needs a FILE")
        json_path = rest[i + 1]
        del rest[i:i + 2]
    buf = io.StringIO()
    real = sys.stdout

    class Tee(io.TextIOBase):
        def write(self, text):
            buf.write(text)
            return real.write(text)

        def flush(self):
            real.flush()

    with contextlib.redirect_stdout(Tee()):
        try:
            rc = probe.main([args.probe, *rest])
        except SystemExit as exc:  # the probe's argparse: -h or a usage error
            return int(exc.code or 0) if isinstance(exc.code, int) else 2
    if json_path:
        rows = [json.loads(line) for line in buf.getvalue().splitlines() if line.startswith("{")]
        try:
            with open(json_path, "w", encoding="utf-8") as f:
                json.dump(rows, f, indent=1)
        except OSError as exc:
            raise InputError(f"--json {json_path}: cannot write ({exc})") from None
    return rc
