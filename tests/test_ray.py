"""Ray backends (issue 8): on a local Ray cluster on loopback, the estimation sweep gives the same
numbers as the local process pool, survives a killed worker, and RLlib trains the shared policy
through ``ParallelPettingZooEnv``."""

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
DURATION_S = 8.0  # simulated seconds per case: about a second of wall time, enough for updates


def _load_script(name: str):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # Ray ships the script's functions by value (it needs the name)
    spec.loader.exec_module(module)
    return module


bench = _load_script("benchmark_estimation")


def test_ray_backends_say_how_to_install_ray(monkeypatch):
    # First in this file: Ray's own threads must not be running while ray is hidden.
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    with pytest.raises(ImportError, match=r"astrocargo\[ray\]"):
        bench.import_ray()
    with pytest.raises(SystemExit):
        bench.main(["--suite", "smoke", "--backend", "ray", "--out-dir", "unused"])


@pytest.fixture(scope="module")
def ray_address():
    """A one-node Ray cluster with 2 CPUs on 127.0.0.1, started by this process."""
    # Before Ray's first import: bind the node to the loopback address, not the host's.
    old = os.environ.get("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    ray = pytest.importorskip("ray")
    # "local": a new instance even if another cluster was started on this machine.
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
        if old is None:
            os.environ.pop("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", None)
        else:
            os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = old


def _script(name: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run(
        [sys.executable, str(SCRIPTS / f"{name}.py"), *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _cases(out_dir: Path) -> dict[str, dict]:
    """Every case's result by file name, without its wall time (the one field that may differ)."""
    results = {}
    for path in sorted((out_dir / "cases").glob("*.json")):
        result = json.loads(path.read_text())
        result.pop("wall_s")
        results[path.name] = result
    return results


def test_local_and_ray_backends_give_identical_results(ray_address, tmp_path):
    sweep = ["--suite", "sweep", "--seeds", "4", "--duration", str(DURATION_S)]
    local = _script(
        "benchmark_estimation", *sweep, "--workers", "2", "--out-dir", str(tmp_path / "l")
    )
    assert local.returncode == 0, local.stderr
    # A second driver joins the cluster at its address, as on a real cluster.
    on_ray = _script(
        "benchmark_estimation",
        *sweep,
        "--backend",
        "ray",
        "--ray-address",
        ray_address,
        "--out-dir",
        str(tmp_path / "r"),
    )
    assert on_ray.returncode == 0, on_ray.stderr
    expected = _cases(tmp_path / "l")
    assert len(expected) == 4
    assert _cases(tmp_path / "r") == expected
    # The sweep draws a different cargo per seed.
    assert len({r["case"]["cargo_mass"] for r in expected.values()}) == 4


def _ppid(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[1])


def _kill_first_case_worker(stop: threading.Event, killed: list[int]) -> None:
    """SIGKILL the first Ray worker of this process's cluster seen running a case
    (worker -> raylet -> this process)."""
    while not stop.is_set():
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            pid = int(entry)
            try:
                title = Path(f"/proc/{pid}/cmdline").read_bytes()
                ours = _ppid(_ppid(pid)) == os.getpid()
            except (OSError, ValueError, IndexError):
                continue  # exited meanwhile
            if ours and title.startswith(b"ray::run_case"):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
        time.sleep(0.02)


def test_sweep_survives_a_killed_worker(ray_address, tmp_path):
    cases = bench.sweep_cases(3, DURATION_S)
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=_kill_first_case_worker, args=(stop, killed), daemon=True)
    killer.start()
    try:
        results = bench.run_all(cases, tmp_path, workers=1, backend="ray")
    finally:
        stop.set()
        killer.join()
    assert killed, "no worker was seen running a case"
    assert [r["case"]["seed"] for r in results] == [0, 1, 2]
    # Every case written, with the numbers a run in this process gives (the killed one included).
    written = _cases(tmp_path)
    assert len(written) == 3
    for case in cases:
        expected = bench.run_case(case)
        expected.pop("wall_s")
        path = bench.case_path(tmp_path, case)
        assert written[path.name] == json.loads(json.dumps(expected, default=bench._json_default))


def test_rllib_trains_the_shared_policy_on_the_cluster(ray_address, tmp_path):
    log_dir = tmp_path / "rllib"
    run = _script(
        "train",
        "--backend",
        "rllib",
        "--ray-address",
        ray_address,
        "--env-runners",
        "2",
        "--robots",
        "2",
        "--max-cycles",
        "25",
        "--timesteps",
        "400",  # 2 iterations of 100 environment steps x 2 robots
        "--seed",
        "5",
        "--hyperparams",
        "train_batch_size_per_learner=100",
        "minibatch_size=50",
        "num_epochs=1",
        "--log-dir",
        str(log_dir),
    )
    assert run.returncode == 0, run.stderr
    config = json.loads((log_dir / "config.json").read_text())
    assert config["backend"] == "rllib" and config["seed"] == 5
    assert config["iterations"] == 2 and config["samples"] == 400
    rows = list(csv.DictReader((log_dir / "progress.csv").open()))
    assert [int(r["samples"]) for r in rows] == [200, 400]
    assert all(np.isfinite(float(r["robot_return_mean"])) for r in rows)

    # The checkpoint holds the one shared policy, which acts on a robot's observation.
    import torch
    from ray.rllib.core.rl_module.rl_module import RLModule

    from astrocargo.envs import astrobee_cargo_v0

    module = RLModule.from_checkpoint(
        str(log_dir / "checkpoint" / "learner_group" / "learner" / "rl_module" / "shared")
    )
    env = astrobee_cargo_v0.parallel_env(**config["env_kwargs"])
    obs, _ = env.reset(seed=0)
    batch = torch.as_tensor(np.stack(list(obs.values())), dtype=torch.float32)
    out = module.forward_inference({"obs": batch})
    env.close()
    action_dim = env.action_space("astrobee_0").shape[0]
    assert out["action_dist_inputs"].shape == (2, 2 * action_dim)  # Gaussian mean and log std
