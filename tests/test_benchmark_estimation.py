"""The estimation benchmark writes each finished case at once and resumes after a kill."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "benchmark_estimation.py"
ARGS = ["--suite", "smoke", "--duration", "8", "--workers", "1"]


def _run(out_dir: Path) -> subprocess.Popen:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.Popen(
        [sys.executable, str(SCRIPT), *ARGS, "--out-dir", str(out_dir)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen) -> None:
    """Wait for a run reading its stderr as it goes (a full pipe would block ``wait``), and
    close the pipe."""
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err


def _analysis(out_dir: Path) -> list[dict]:
    """Results without the fields that legitimately differ between runs (wall time)."""
    cases = json.loads((out_dir / "results.json").read_text())["cases"]
    for c in cases:
        c.pop("wall_s")
    return cases


def test_killed_run_resumes_to_the_same_results(tmp_path):
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    _finish(_run(clean))

    proc = _run(killed)
    cases_dir = killed / "cases"
    deadline = time.time() + 300
    while time.time() < deadline and not (cases_dir.exists() and any(cases_dir.glob("*.json"))):
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()  # reaps it and closes its stderr pipe
    finished = list(cases_dir.glob("*.json"))
    assert 1 <= len(finished) < 3, "the kill should land between the first and the last case"
    for f in finished:
        json.loads(f.read_text())  # readable: written atomically
    assert not (killed / "results.json").exists()

    _finish(_run(killed))
    assert _analysis(killed) == _analysis(clean)


def _module():
    from test_scripts import load

    return load("benchmark_estimation")


def test_time_to_certainty_is_when_the_spread_stays_below_its_target():
    bench = _module()
    times = [1.0, 2.0, 3.0, 4.0]
    # 2 sigma: mass 3, 0.8, 1.2, 0.8 % -> stays below 1 % from 4 s; CoM always below 5 mm;
    # the worst principal moment never below 5 %.
    spreads = [
        {"mass_rel": m / 200, "com_m": 0.001, "principal_rel": [0.01, 0.03, 0.2]}
        for m in (3.0, 0.8, 1.2, 0.8)
    ]
    got = bench.time_to_certainty(times, spreads)
    assert got == {"mass_rel": 4.0, "com_m": 1.0, "principal_rel": None}


def test_excite_without_a_design_is_a_no_design_row(monkeypatch):
    """A team size without a shipped design (simulated: every size ships one now) reports "no
    design" at once, and the time-to-certainty table says so instead of failing."""
    import astrocargo.agents.excitation

    monkeypatch.setattr(astrocargo.agents.excitation, "has_design", lambda n: False)
    bench = _module()
    case = bench.Case(bench.certainty_name("excite", 1), robots=1, trajectory="excite", seed=0)
    result = bench.run_case(case)
    assert result["no_design"] is True and result["wall_s"] == 0.0
    cert = bench.summarise_certainty([result])
    assert cert["rows"]["excite, 1"]["no_design"] is True
    assert "| excite | 1 | - | no design |" in bench.certainty_markdown(cert)
    names = {c.name for c in bench.certainty_cases(1, 90.0)}
    assert names == {
        bench.certainty_name(t, n)
        for t in bench.CERTAINTY_TRAJECTORIES
        for n in bench.CERTAINTY_ROBOTS
    }
