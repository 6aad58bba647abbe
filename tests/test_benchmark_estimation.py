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


def _analysis(out_dir: Path) -> list[dict]:
    """Results without the fields that legitimately differ between runs (wall time)."""
    cases = json.loads((out_dir / "results.json").read_text())["cases"]
    for c in cases:
        c.pop("wall_s")
    return cases


def test_killed_run_resumes_to_the_same_results(tmp_path):
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    proc = _run(clean)
    assert proc.wait(timeout=600) == 0, proc.stderr.read()

    proc = _run(killed)
    cases_dir = killed / "cases"
    deadline = time.time() + 300
    while time.time() < deadline and not (cases_dir.exists() and any(cases_dir.glob("*.json"))):
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = list(cases_dir.glob("*.json"))
    assert 1 <= len(finished) < 3, "the kill should land between the first and the last case"
    for f in finished:
        json.loads(f.read_text())  # readable: written atomically
    assert not (killed / "results.json").exists()

    proc = _run(killed)
    assert proc.wait(timeout=600) == 0, proc.stderr.read()
    assert _analysis(killed) == _analysis(clean)
