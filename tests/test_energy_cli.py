"""``scmr energy`` commands and the measured-input helpers."""

from __future__ import annotations

import json

import pytest

from scmr_mesh.cli import main
from scmr_mesh.energy import (
    EnergyLedger,
    LinkEstimator,
    Placement,
    cycles_from_cpu_time,
)
from scmr_mesh.energy.commands import parse_rate, parse_size
from scmr_mesh.energy.experiments import eq49_table
from scmr_mesh.energy.measure import _parse_cpuinfo
from scmr_mesh.errors import InputError


def test_units():
    assert parse_size("1MB") == 1048576 and parse_size("250000") == 250000 and parse_size("0.5MB") == 524288
    assert parse_rate("23Mb/s") == 3014656 and parse_rate("28Mb/s") == 3670016
    assert parse_rate("1MB/s") == 1048576 and parse_rate("1000") == 1000
    for bad in ("fast", "1 parsec", "-3Mb/s", "0"):
        with pytest.raises(InputError):
            parse_rate(bad)
    with pytest.raises(InputError):
        parse_size("3 furlongs")


def test_cycles_from_cpu_time_and_cpuinfo():
    assert cycles_from_cpu_time(0.25, 2e9) == 5e8
    assert cycles_from_cpu_time(0.25, 2e9, cpi_ratio=2.0) == 1e9
    assert cycles_from_cpu_time(1.0) > 0  # host clock from /proc/cpuinfo or the fallback
    with pytest.raises(InputError):
        cycles_from_cpu_time(-1, 2e9)
    text = "processor\t: 0\ncpu MHz\t\t: 2000.000\nprocessor\t: 1\ncpu MHz\t\t: 3000.000\n"
    assert _parse_cpuinfo(text) == 2.5e9
    assert _parse_cpuinfo("model name: x\n") is None


def test_link_estimator_ewma():
    est = LinkEstimator(alpha=0.5)
    assert est.estimate("cloud") is None
    # 1000 B up + 1000 B down in 1.5 s of which the server took 0.5 s: 2000 B/s
    assert est.observe("cloud", bytes_up=1000, bytes_down=1000, elapsed_s=1.5, server_s=0.5) == 2000
    assert est.observe("cloud", bytes_up=2000, bytes_down=2000, elapsed_s=1.0) == 0.5 * 4000 + 0.5 * 2000
    link = est.estimate("cloud")
    assert link.measured and link.up_Bps == link.down_Bps == 3000
    assert set(est.estimates()) == {"cloud"} and est.observations("cloud") == 2


def test_ledger_sums_per_tier():
    led = EnergyLedger("r1", "robot1")
    mk = lambda tier, e, missed=False: Placement(tier, e, 1.0, missed, "", [])  # noqa: E731
    led.record(mk("cloud", 2.0))
    led.record(mk("cloud", 3.0))
    led.record(mk("local", 10.0, True))
    led.record(mk("cloud", 1.0), tier="leader", energy_j=4.0)
    s = led.summary()
    assert s["total_j"] == 19.0 and s["requests"] == 4 and s["deadline_missed"] == 1
    assert s["per_tier"]["cloud"] == {"energy_j": 5.0, "requests": 2}
    assert s["per_tier"]["leader"] == {"energy_j": 4.0, "requests": 1}


def test_table_command_json(tmp_path, capsys):
    out = tmp_path / "t.json"
    assert main(["energy", "table", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["rows"] == eq49_table()["rows"]
    printed = capsys.readouterr().out
    assert all(r["profile"] in printed for r in doc["rows"])


def test_sweep_command_json_and_plot(tmp_path):
    js, png = tmp_path / "s.json", tmp_path / "s.png"
    rc = main(["energy", "sweep", "--sizes", "1MB,3MB", "--bandwidths", "10Mb/s,50Mb/s,90Mb/s",
               "--profile", "leader,robot1", "--json", str(js), "--plot", str(png)])
    assert rc == 0
    doc = json.loads(js.read_text())
    assert [p["profile"] for p in doc["profiles"]] == ["leader", "robot1"]
    assert len(doc["profiles"][0]["grid"]) == 6
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_place_command_explains(tmp_path, capsys):
    js = tmp_path / "p.json"
    rc = main(["energy", "place", "--profile", "robot1", "--cycles", "5e9", "--up", "1MB", "--down", "1MB",
               "--bandwidth-up", "23Mb/s", "--bandwidth-down", "28Mb/s", "--reachable", "leader",
               "--deadline", "0.01", "--json", str(js)])
    assert rc == 0
    doc = json.loads(js.read_text())
    assert doc["tier"] in ("local", "leader") and doc["deadline_missed"] is True
    assert "DEADLINE MISSED" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["energy", "place", "--profile", "robot9", "--cycles", "1", "--up", "1", "--down", "1",
          "--bandwidth-up", "1"], "robot9"),
        (["energy", "place", "--profile", "robot1", "--up", "1", "--down", "1", "--bandwidth-up", "1"],
         "--cycles"),
        (["energy", "place", "--profile", "robot1", "--cycles", "1", "--up", "1", "--down", "1",
          "--bandwidth-up", "1", "--reachable", "moon"], "moon"),
        (["energy", "sweep", "--sizes", "big"], "big"),
    ],
)
def test_errors_are_one_line(argv, needle, capsys):
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("scmr: error:") and needle in err[0]


def test_bad_profiles_file_via_cli(tmp_path, capsys):
    f = tmp_path / "bad.toml"
    f.write_text("[profiles.x]\np_compute_w = 1\n")
    assert main(["energy", "profiles", "--profiles-file", str(f)]) == 1
    err = capsys.readouterr().err
    assert str(f) in err and "profiles.x." in err


def test_measured_inputs_report_uses_medians_and_marks_inputs():
    from scmr_mesh.energy import PROFILES
    from scmr_mesh.energy.experiments import measured_inputs_report

    samples = [{"cpu_s": c, "bytes_up": u, "bytes_down": d}
               for c, u, d in [(0.01, 1000, 10), (0.02, 3000, 30), (0.05, 2000, 20)]]
    rep = measured_inputs_report(samples, [PROFILES["robot1"]], host_hz=2e9, host_hz_source="given",
                                 up_Bps=1e6, down_Bps=1e6)
    assert rep["cycles"]["median"] == pytest.approx(0.02 * 2e9)
    assert rep["inputs"]["bytes_up"]["value"] == 2000 and rep["inputs"]["bytes_down"]["value"] == 20
    assert rep["inputs"]["cycles"]["source"].startswith("measured")
    assert rep["inputs"]["up_Bps"]["source"] == "assumed"
    row = rep["rows"][0]
    # E_proc = 47 W * 4e7 / 1e9 = 1.88 J; E_cloud = 25 * 4e7 / 3e11 + 83.54 * 2000/1e6 + 104.08 * 20/1e6
    assert row["e_proc_j"] == pytest.approx(1.88)
    assert row["e_cloud_j"] == pytest.approx(25 * 4e7 / 3e11 + 0.16708 + 0.0020816)
    assert row["decision"] == "offload"


def test_bench_energy_rejects_missing_data(tmp_path, capsys):
    assert main(["bench", "energy", "--data", str(tmp_path / "nope")]) == 1
    assert "--data" in capsys.readouterr().err


def test_public_api_names():
    import scmr_mesh.energy as energy

    required = {"Profile", "PROFILES", "get_profile", "Task", "LinkEstimate", "Placement", "choose_placement",
                "energy_terms", "cycles_from_cpu_time"}
    assert required <= set(energy.__all__)
    assert all(hasattr(energy, n) for n in energy.__all__)
