"""``scmr thesis``: the dissertation's figures shipped as facts, the pieces of the report, and one
reduced ``--quick`` run checked for structure and for where every number came from.

The run (2 robots x 2 images, fleet sizes 1 and 2, a 1.5 s time unit, proxy backend, real
pipeline) takes about 45 s; the rest is pure and takes a few seconds.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from scmr_mesh.energy import PROFILES
from scmr_mesh.thesis import fit
from scmr_mesh.thesis.cpu import CpuSampler, cpu_between
from scmr_mesh.thesis.facts import load_facts, normalise, table_4_2
from scmr_mesh.thesis.plan import ThesisConfig, estimate_s, plan_runs, stages

from conftest import SHARED

DISSERTATION = SHARED / "seed" / "000_75df71bbe1ed0f6b.txt"
SHARED_TABLE_4_2 = SHARED / "data" / "thesis_table_4_2.csv"
WORDS = {"three": 3}


# ------------------------------------------------------------------------------- facts
def test_every_fact_is_quoted_verbatim_from_the_dissertation():
    if not DISSERTATION.is_file():
        pytest.skip(f"the dissertation's text is not at {DISSERTATION}")
    text = normalise(DISSERTATION.read_text(encoding="utf-8"))
    missing = [k for k, f in load_facts().items() if normalise(f.quote) not in text]
    assert missing == []


def test_every_fact_value_is_printed_in_its_quote():
    for k, f in load_facts().items():
        q = f.quote.replace(" ", "")
        for name, v in f.values.items():
            shown = str(int(v)) if float(v).is_integer() else str(v)
            assert shown in q or any(w in f.quote and n == v for w, n in WORDS.items()), (k, name, v)
        assert re.search(r"(Table|Figure|Sec|Eq) \d", f.source), k


def test_table_4_2_is_the_published_one():
    import csv

    shipped = table_4_2()
    assert len(shipped) == 20 and {r["robot_id"] for r in shipped} == {"robot1", "robot2", "robot3", "robot4"}
    if SHARED_TABLE_4_2.is_file():
        with open(SHARED_TABLE_4_2, encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        assert [{k: str(r[k]) for k in rows[0]} for r in shipped] == rows
    if DISSERTATION.is_file():  # every row, tab-separated, as printed in the text's Table 4.2
        text = DISSERTATION.read_text(encoding="utf-8")
        for r in shipped:
            line = "\t".join(str(r[k]) for k in ("robot", "image_set", "image", "description", "original_bytes",
                                                 "upload_start_ms", "upload_end_ms"))
            assert line in text, line
    r = shipped[0]
    assert r["cloud_tor_ms"] == r["download_end_ms"] - r["upload_start_ms"] == 2648


def test_table_4_3_facts_are_the_built_in_profiles():
    q = load_facts()["table43"].quote
    nums = [float(x) for x in re.findall(r"(\d+(?:\.\d+)?)(?:W|GHz)", q)]
    order = ("leader", "robot1", "robot2", "robot3", "robot4")
    cols = {p: [nums[i + 5 * j] for j in range(5)] for i, p in enumerate(order)}
    for p in order:
        pr = PROFILES[p]
        assert cols[p] == [pr.p_compute_w, pr.p_idle_w, pr.p_up_w, pr.p_down_w, pr.clock_hz / 1e9]


# ------------------------------------------------------------------------------- pure pieces
def test_plan_timeline_and_scenarios_are_valid():
    from scmr_mesh.scenario.spec import parse_scenario

    cfg = ThesisConfig(quick=True)
    runs = plan_runs(cfg)
    assert list(runs) == ["noloss", "loss", "size1", "size2", "size4"]
    loss = runs["loss"]
    cuts = [(f["at_s"], f.get("link") or f.get("groups")) for f in loss["faults"]]
    assert cuts[:4] == [(2.0 * k, [f"robot{k}", "cloud"]) for k in range(1, 5)]
    assert cuts[4][0] == 8.0 and loss["duration_s"] == 13.0
    assert all(f["at_s"] + f["for_s"] == 11.0 for f in loss["faults"])  # all heal together
    assert [s["k"] for s in stages(cfg)] == [0, 1, 2, 3, 4]
    for sc in runs.values():
        parse_scenario(sc)
    assert runs["size4"]["fleet"]["robots"][3]["profile"] == "robot4"
    big = plan_runs(ThesisConfig(fleet_sizes=(1, 6)))["size6"]["fleet"]["robots"]
    assert [r["image_set"] for r in big] == ["set1", "set2", "set3", "set4", "set1", "set2"]
    assert estimate_s(cfg) < 300 and estimate_s(ThesisConfig()) > estimate_s(cfg)


@pytest.mark.parametrize("kw, msg", [
    (dict(robots=5), "--robots"), (dict(images=0), "--images"), (dict(fleet_sizes=(4,)), "--fleet-sizes"),
])
def test_config_errors_name_the_flag(kw, msg):
    from scmr_mesh.errors import InputError

    with pytest.raises(InputError, match=msg):
        ThesisConfig(**kw).check()


def test_model_choice_by_leave_one_out():
    xs = [1, 2, 4, 8, 16]
    assert fit.choose(xs, [3.0, 3.1, 2.9, 3.05, 2.95], ("const", "log", "linear"))["chosen"] == "const"
    assert fit.choose(xs, [2 + 0.5 * x for x in xs], ("const", "log", "linear"))["chosen"] == "linear"
    assert fit.choose(xs, [1 + math.log2(x) for x in xs], ("const", "log", "linear"))["chosen"] == "log"
    assert fit.choose([1, 2, 3, 4], [2 ** x for x in (1, 2, 3, 4)], ("const", "linear", "exp"))["chosen"] == "exp"
    f = fit.fit("linear", [0, 1, 2, 3], [1, 3, 5, 7.5])
    assert f["b"] == pytest.approx(2.15) and f["slope_se"] > 0


def test_cpu_sampler_measures_a_process_group(tmp_path):
    ready = tmp_path / "ready"
    ready.mkdir()
    burn = ("import json,os,sys,time\n"
            f"open({str(ready / 'burner')!r},'w').write(json.dumps({{'pid': os.getpid()}}))\n"
            "t=time.process_time()\n"
            "while time.process_time()-t<0.4: pass\n"
            "time.sleep(0.3)\n")
    with CpuSampler(ready, period_s=0.05) as s:
        p = subprocess.Popen([sys.executable, "-c", burn], start_new_session=True)
        p.wait(timeout=30)
    series = s.series["burner"]
    used = cpu_between(series, series[0][0], series[-1][0])
    assert series[-1][1] >= 0.35 and used is not None and used >= 0.2


# ------------------------------------------------------------------------------- one reduced run
def _numbers(obj, path=()):
    if isinstance(obj, bool) or obj is None:
        return
    if isinstance(obj, (int, float)):
        yield path, obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numbers(v, path + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numbers(v, path + (i,))


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory, roads_dir):
    out = tmp_path_factory.mktemp("thesis") / "report"
    t = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "thesis", "--quick", "--robots", "2", "--images", "2",
                        "--fleet-sizes", "1,2", "--step", "1.5", "--backend", "proxy", "--data", str(roads_dir),
                        "--out", str(out)],
                       capture_output=True, text=True, timeout=280)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return out, r, time.monotonic() - t


@pytest.mark.timeout(300)
def test_quick_run_report_structure(quick_run):
    out, r, _ = quick_run
    assert "expect about" in r.stderr and "[1/4] noloss" in r.stderr and "[4/4] size2" in r.stderr
    assert "experiment 7" in r.stdout
    rep = json.loads((out / "report.json").read_text())
    facts = load_facts()
    assert sorted(rep["experiments"], key=int) == [str(i) for i in range(1, 8)]
    import cv2

    for k, e in rep["experiments"].items():
        assert {"claim", "ours", "holds", "figures"} <= set(e), k
        h = e["holds"]
        assert h is True or h is False or (isinstance(h, str) and h.startswith("not comparable: ")), (k, h)
        assert e["figures"], k
        for fig in e["figures"]:
            img = cv2.imread(str(out / fig))
            assert fig.endswith(".png") and img is not None and img.size > 0, fig
        for c in [e["claim"]] + [x["claim"] for x in e.get("checks", [])]:
            assert c["values"] == facts[c["fact"]].values and c["quote"] == facts[c["fact"]].quote
            assert re.search(r"(Table|Figure) \d\.\d+", c["source"] + e["claim"]["source"]), c["source"]
        for fid in e["inputs"]["cited"]:
            assert fid in facts or fid == "table_4_2", fid
        for name, a in e["inputs"]["assumed"].items():
            assert a["why"], name
    # experiments 1 and 4: every image served, by the cloud and by the leader, four rows each
    assert rep["experiments"]["1"]["ours"]["served"] == 4 and rep["experiments"]["4"]["ours"]["served"] == 4
    assert {Path(f).name for f in rep["experiments"]["4"]["figures"]} >= {"exp4_robot1.png", "exp4_robot2.png"}
    # experiments 2/5: Table 4.2 side by side, per robot and image
    rows = rep["experiments"]["5"]["ours"]["per_image"]
    assert [(x["robot"], x["thesis_image"]) for x in rows] == [
        ("robot1", "Image1.png"), ("robot1", "Image5.png"), ("robot2", "Image6.png"), ("robot2", "Image8.png")]
    assert all(x["leader_tor_p50_ms"] and x["cloud_tor_p50_ms"] for x in rows)
    assert set(rep["model"]) == {"table_4_4", "eq_3_14", "eq_3_18_19"}
    assert rep["model"]["table_4_4"]["per_fleet_size"][0]["robots"] == 1
    md = (out / "report.md").read_text()
    from scmr_mesh.thesis.report import markdown

    assert md == markdown(rep)
    assert "Figure 4.21" in md and "Table 4.4" in md and "![exp7_sweep](figures/exp7_sweep.png)" in md


@pytest.mark.timeout(300)
def test_every_number_comes_from_the_raw_data_or_a_cited_table(quick_run, tmp_path):
    """Rebuilt from the run's raw files the report is the same; change a measurement and ours changes."""
    from scmr_mesh.thesis import analysis

    out, _, _ = quick_run
    rep = json.loads((out / "report.json").read_text())
    again = json.loads(json.dumps(analysis.build(out, draw=False), default=str))
    for k, e in rep["experiments"].items():  # the same but for the figures (not drawn this time)
        assert {**again["experiments"][k], "figures": e["figures"]} == e, k
    assert again["model"]["eq_3_14"] == rep["model"]["eq_3_14"]
    assert {**again["model"]["table_4_4"], "figures": []} == {**rep["model"]["table_4_4"], "figures": []}
    # claims: every number of a claim is a fact's
    facts = load_facts()
    for k, e in rep["experiments"].items():
        for c in [e["claim"]] + [x["claim"] for x in e.get("checks", [])]:
            fact_numbers = set(facts[c["fact"]].values.values())
            assert all(v in fact_numbers for _, v in _numbers(c["values"])), k
    # ours: scale every measured ToR of the no-loss run by 10 and the leader's CPU in the loss run by 2
    twin = tmp_path / "twin"
    shutil.copytree(out, twin, symlinks=True)
    for f in (twin / "runs" / "noloss" / "robots").glob("*/records.jsonl"):
        recs = [json.loads(x) for x in f.read_text().splitlines() if x.strip()]
        for x in recs:
            x["tor_ms"] = x["tor_ms"] * 10
        f.write_text("".join(json.dumps(x) + "\n" for x in recs))
    cpu_file = twin / "runs" / "loss" / "cpu.json"
    cpu = json.loads(cpu_file.read_text())
    cpu["series"]["leader"] = [[t, 2 * v] for t, v in cpu["series"]["leader"]]
    cpu_file.write_text(json.dumps(cpu))
    changed = analysis.build(twin, draw=False)
    o2, c2 = rep["experiments"]["2"]["ours"], changed["experiments"]["2"]["ours"]
    assert c2["tor_p50_ms"] == pytest.approx(10 * o2["tor_p50_ms"], rel=1e-3)
    w, w2 = (rep["experiments"]["6"]["ours"]["leader_serving_w_by_k"],
             changed["experiments"]["6"]["ours"]["leader_serving_w_by_k"])
    assert all(w2[k] == pytest.approx(2 * w[k], rel=1e-3, abs=1e-3) for k in w)
    # and the experiments that use no run of the twin's changes stay put
    assert changed["experiments"]["7"]["ours"]["break_even_mbps"] == rep["experiments"]["7"]["ours"]["break_even_mbps"]


def test_reanalyse_refuses_a_folder_without_a_run(tmp_path):
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "thesis", "--reanalyse", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "no scmr thesis run" in r.stderr


def test_out_holding_other_files_is_refused(tmp_path):
    (tmp_path / "precious.txt").write_text("keep me")
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "thesis", "--quick", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "not written by scmr thesis" in r.stderr
    assert (tmp_path / "precious.txt").read_text() == "keep me"
