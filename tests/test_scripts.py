"""Command lines of the scripts: every bad input ends in the parser's error (usage, a message,
exit status 2) before anything runs, vectors may start with a minus sign, and --help shows the
defaults. The scripts' parsers run in-process (no simulation starts)."""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from astrocargo.estimator.ukf import InertialParamUKF as UKF

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
TWO_ROBOT_DESIGN = SCRIPTS.parent / "agents" / "designs" / "excite_2robots.json"


def load(name: str):
    """scripts/NAME.py as a module (its main() is not run)."""
    spec = importlib.util.spec_from_file_location(f"_script_{name}", SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def scripts():
    names = ("demo", "benchmark_estimation", "benchmark_performance", "soak", "train")
    more = ("evaluate", "render_scene", "estimation_limits", "window_bias")
    return {name: load(name) for name in names + more}


def parser_error(parse, argv: list[str], capsys) -> str:
    """The message of the parser's error for argv (fails if argv is accepted)."""
    with pytest.raises(SystemExit) as exc:
        parse(argv)
    assert exc.value.code == 2, f"{argv}: exit status {exc.value.code}, expected 2"
    err = capsys.readouterr().err
    assert "usage:" in err and "error:" in err, err
    return err.split("error:", 1)[1].strip()


# --------------------------------------------------------------------------- benchmark_estimation


@pytest.mark.parametrize(
    "spelling",
    [
        ["--cargo-com", "-0.045,0.012,-0.03"],  # comma-separated after a space
        ["--cargo-com=-0.045,0.012,-0.03"],  # comma-separated with "="
        ["--cargo-com", "-0.045", "0.012", "-0.03"],  # three values
    ],
)
def test_vectors_may_start_with_a_minus_sign(scripts, tmp_path, spelling):
    args = scripts["benchmark_estimation"].parse_args(
        ["--robots", "2", *spelling, "--cargo-inertia", "0.07,0.10,0.11,0.005,0,-0.004"]
        + ["--out", str(tmp_path / "case.json")]
    )
    assert args.cargo_com == (-0.045, 0.012, -0.03)
    assert args.cargo_inertia == (0.07, 0.10, 0.11, 0.005, 0.0, -0.004)


def test_vector_defaults_are_kept(scripts, tmp_path):
    module = scripts["benchmark_estimation"]
    args = module.parse_args(["--out-dir", str(tmp_path)])
    assert args.cargo_com == module.CARGO_COM and args.cargo_inertia == module.CARGO_INERTIA


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--suite", "smoke", "--duration", "1"], "--duration must be at least 8"),
        (["--seeds", "0"], "--seeds: must be a positive integer"),
        (["--workers", "0"], "--workers: must be a positive integer"),
        (["--duration", "-3"], "--duration: must be a positive number"),
        (["--duration", "nan"], "--duration: must be finite"),
        (["--robots", "2", "--cargo-com", "0.1,0.2"], "expected 3 numbers"),
        (["--robots", "2", "--cargo-com", "0.1,x,0.2"], "not a number"),
        (["--robots", "2", "--cargo-inertia", "1", "2", "3"], "expected 6 numbers"),
        (["--robots", "0"], "--robots must be in 1.."),
        (["--robots", "2", "--seed", "-1"], "--seed: must be an integer >= 0"),
        (["--robots", "2", "--comm-drop", "1"], "--comm-drop must be a probability below 1"),
        (["--robots", "2", "--cargo-mass", "0"], "--cargo-mass: must be a positive number"),
        (["--trajectory", "circle"], "unknown trajectory 'circle'"),
        (["--trajectory", "nowhere.json"], "'nowhere.json' does not exist"),
        (["--robots", "3", "--trajectory", str(TWO_ROBOT_DESIGN)], "designed for 2 robots"),
        (["--out-dir", "/dev/null/x"], "--out-dir: cannot create folder"),
    ],
)
def test_benchmark_estimation_rejects(scripts, capsys, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)  # the default output folders land here
    assert message in parser_error(scripts["benchmark_estimation"].parse_args, argv, capsys)


def test_benchmark_estimation_prints_the_seeds_it_uses(scripts):
    module = scripts["benchmark_estimation"]
    smoke = module.smoke_cases(8.0)
    assert module.seed_list(smoke) == ", ".join(map(str, sorted({c.seed for c in smoke})))
    assert module.seed_list(module.standard_cases(5, 8.0)) == "0..4"


# --------------------------------------------------------------------------- benchmark_performance


@pytest.mark.parametrize(
    "content, message", [("", "is empty"), ("{oops", "is not JSON"), ("[1, 2]", "not an object")]
)
def test_benchmark_performance_checks_its_json_file_first(
    scripts, capsys, tmp_path, content, message
):
    path = tmp_path / "bench.json"
    path.write_text(content)
    assert message in parser_error(
        scripts["benchmark_performance"].parse_args, ["--json", str(path)], capsys
    )


def test_benchmark_performance_accepts_a_new_or_its_own_json_file(scripts, tmp_path):
    parse = scripts["benchmark_performance"].parse_args
    assert parse(["--json", str(tmp_path / "new.json")]).json == tmp_path / "new.json"
    own = tmp_path / "own.json"
    own.write_text(json.dumps({"env": {"1": {"step_us": 1.0}}}))
    assert parse(["--json", str(own)]).json == own


# --------------------------------------------------------------------------- demo


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--video", "x.gif", "--video-every", "0"], "--video-every: must be a positive integer"),
        (["--seed", "-1"], "--seed: must be an integer >= 0"),
        (["--duration", "0.001"], "--duration must be at least one control period"),
        (["--duration", "0"], "--duration: must be a positive number"),
        (["--robots", "9"], "--robots must be in 1..8"),
        (["--out-dir", "/dev/null/x"], "--out-dir: cannot create folder"),
        (["--video", "/dev/null/x.gif"], "--video's folder: cannot create folder"),
        (["--video", "out.mp4"], "--video must end in .gif"),
        (["--noise", "loud"], "invalid choice"),
        (["--trajectory", "circle"], "unknown trajectory 'circle'"),
        (["--trajectory", "nowhere.json"], "'nowhere.json' does not exist"),
        (["--robots", "3", "--trajectory", str(TWO_ROBOT_DESIGN)], "designed for 2 robots"),
        (["--compare", "circle"], "unknown trajectory 'circle'"),
        (["--robots", "3", "--compare", str(TWO_ROBOT_DESIGN)], "designed for 2 robots"),
    ],
)
def test_demo_rejects(scripts, capsys, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert message in parser_error(scripts["demo"].parse_args, argv, capsys)


def test_demo_flies_figure8_yaw_beside_excite_by_default(scripts, tmp_path):
    args = scripts["demo"].parse_args(["--out-dir", str(tmp_path)])
    assert (args.compare, args.trajectory) == ("figure8_yaw", "excite")
    alone = scripts["demo"].parse_args(["--out-dir", str(tmp_path), "--compare", "none"])
    assert alone.compare == "none"


def test_demo_creates_its_folders_first_and_keeps_the_video_path(scripts, tmp_path):
    out, video = tmp_path / "a" / "b", tmp_path / "elsewhere" / "x.gif"
    args = scripts["demo"].parse_args(["--out-dir", str(out), "--video", str(video)])
    assert out.is_dir() and video.parent.is_dir()
    assert Path(args.video) == video


# --------------------------------------------------------------------------- soak, train, evaluate


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--duration", "-5"], "--duration: must be a positive number"),
        (["--duration", "5"], "--duration must be at least 10 s"),
        (["--duration", "20", "--check-every", "2000"], "must cover at least one check"),
        (["--check-every", "0"], "--check-every: must be a positive integer"),
        (["--trace-steps", "0"], "--trace-steps: must be a positive integer"),
        (["--robots", "0"], "--robots must be in 1.."),
        (["--noise", "loud"], "invalid choice"),
        (["--json", "/dev/null/x.json"], "--json's folder: cannot create folder"),
    ],
)
def test_soak_rejects(scripts, capsys, argv, message):
    assert message in parser_error(scripts["soak"].parse_args, argv, capsys)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--timesteps", "0"], "--timesteps"),
        (["--copies", "0"], "--copies: must be a positive integer"),
        (["--seed", "-1"], "--seed: must be an integer >= 0"),
        (["--robots", "9"], "--robots must be in 1..8"),
        (["--control-hz", "0"], "--control-hz: must be a positive number"),
        (["--env-runners", "-1"], "--env-runners: must be an integer >= 0"),
        (["--trajectory", "circle"], "invalid choice"),
        (["--log-dir", "/dev/null/x"], "--log-dir: cannot create folder"),
        (["--backend", "rllib", "--algo", "sac"], "--backend rllib trains PPO"),
        (["--hyperparams", "gamma"], "expected KEY=VALUE"),
    ],
)
def test_train_rejects(scripts, capsys, argv, message):
    assert message in parser_error(scripts["train"].parse_args, argv, capsys)


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "give --policy or --curve"),
        (["--policy", "no/such/run"], "--policy: policy must be 'zero', 'scripted' or a run"),
        (["--policy", "zero", "--episodes", "0"], "--episodes: must be a positive integer"),
        (["--policy", "zero", "--seed", "-1"], "--seed: must be an integer >= 0"),
        (["--policy", "zero", "--robots", "0"], "--robots must be in 1.."),
        (["--policy", "zero", "--plot", "c.png"], "--plot draws the learning curves"),
        (["--curve", "no/such/run"], "--curve: no/such/run is not a run folder"),
        (["--policy", "zero", "--json", "/dev/null/x.json"], "--json's folder"),
    ],
)
def test_evaluate_rejects(scripts, capsys, argv, message):
    assert message in parser_error(scripts["evaluate"].parse_args, argv, capsys)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--robots", "0"], "--robots must be in 1.."),
        (["--width", "5000"], "--width must be in 1..1280"),
        (["--out", "scene.jpg"], "--out must end in .png"),
    ],
)
def test_render_scene_rejects(scripts, capsys, argv, message):
    assert message in parser_error(scripts["render_scene"].main, argv, capsys)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--robots", "9"], "--robots must be 1 to 8"),
        (["--duration", "5"], "--duration must be >= 8 s"),
        (["--seeds", "-1"], "--seeds"),
        (["--trajectory", "nowhere.json"], "--trajectory"),
    ],
)
def test_estimation_limits_rejects(scripts, capsys, argv, message):
    assert message in parser_error(scripts["estimation_limits"].parse_args, argv, capsys)


@pytest.mark.parametrize(
    "name",
    [
        "demo",
        "benchmark_estimation",
        "benchmark_performance",
        "soak",
        "train",
        "evaluate",
        "estimation_limits",
        "window_bias",
    ],
)
def test_help_shows_every_default(scripts, capsys, name):
    module = scripts[name]
    with pytest.raises(SystemExit) as exc:
        module.parse_args(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    parser = module.build_parser()
    for action in parser._actions:
        if action.option_strings and action.default is not argparse.SUPPRESS:
            shown = " ".join(out.split())  # help lines are wrapped
            assert f"(default: {action.default})" in shown, (name, action.dest)


def test_window_bias_innovation_stats_tell_white_from_correlated(scripts):
    """The whitened residual's mean square and lag-1 correlation: 1 and 0 for residuals drawn
    from their R, 1 and phi for an AR(1) residual with its stationary covariance."""
    stats = scripts["window_bias"].innovation_stats
    rng = np.random.default_rng(0)
    pi, regressor = rng.standard_normal(10), rng.standard_normal((6, 10))
    root = rng.standard_normal((6, 6)) + 3 * np.eye(6)
    cov = root @ root.T
    for phi in (0.0, 0.8):
        white = rng.standard_normal((4000, 6))
        ar = np.empty_like(white)
        ar[0] = white[0]
        for k in range(1, len(white)):
            ar[k] = phi * ar[k - 1] + np.sqrt(1 - phi**2) * white[k]
        offset = rng.standard_normal(6)
        log = [(regressor @ pi + offset + root @ w, regressor, offset, cov) for w in ar]
        square, lag1 = stats(log, pi)
        assert square == pytest.approx(1.0, abs=0.05)
        assert lag1 == pytest.approx(phi, abs=0.03)


def test_window_bias_score_bias_matches_monte_carlo(scripts):
    """``score_bias`` against the mean score of conditioned updates whose modes follow
    u_t = B u_t-1 + w_t (stationary covariance I, Gm(L) = (B^L)^T, not symmetric), over
    updates at counts 0, 1 and 3, two channels."""
    rng = np.random.default_rng(1)
    n_draws, channels, counts = 100_000, 2, np.array([0, 1, 3])
    rotation = np.linalg.qr(rng.standard_normal((4, 4)))[0]
    step = 0.7 * rotation
    gm = np.stack([np.linalg.matrix_power(step, lag).T for lag in range(4)])
    coefs = rng.standard_normal((3, 6, 6)) * 0.5
    coefs[-1] = np.eye(6)
    d_y = rng.standard_normal((3, channels, 4, 6, 10))
    imu_map = rng.standard_normal((3, channels, 4, 6))
    root = rng.standard_normal((6, 6)) + 3 * np.eye(6)
    cov = root @ root.T
    u = np.empty((4, n_draws, channels, 4))
    u[0] = rng.standard_normal((n_draws, channels, 4))
    for t in range(1, 4):
        fresh = np.sqrt(1 - 0.7**2) * rng.standard_normal((n_draws, channels, 4))
        u[t] = u[t - 1] @ step.T + fresh
    u = u[counts]  # (3, n, c, 4)
    y = np.einsum("sxy,scayp,snca->nxp", coefs, d_y, u)
    r = -np.einsum("sxy,scay,snca->nx", coefs, imu_map, u)
    scores = np.einsum("nxp,xy,ny->np", y, np.linalg.inv(cov), r)
    expected = scripts["window_bias"].score_bias(coefs, d_y, imu_map, gm, counts, cov)
    error = scores.std(axis=0) / np.sqrt(n_draws)
    assert np.all(np.abs(scores.mean(axis=0) - expected) < 4 * error)
    assert np.max(np.abs(expected) / error) > 20  # the bias is far from zero


def test_render_scene_help_shows_defaults(scripts, capsys):
    with pytest.raises(SystemExit):
        scripts["render_scene"].main(["--help"])
    assert "(default: 960)" in capsys.readouterr().out


def test_evaluate_parses_without_torch():
    """evaluate.py --help answers at once: torch and SB3 load after parsing."""
    code = (
        "import runpy, sys; sys.argv = ['evaluate.py', '--help']\n"
        "try:\n    runpy.run_path(sys.argv[0].replace('evaluate.py', r'"
        + str(SCRIPTS / "evaluate.py")
        + "'), run_name='__main__')\nexcept SystemExit:\n    pass\n"
        "assert 'torch' not in sys.modules and 'stable_baselines3' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120, capture_output=True)


def test_same_results_compare_flags_a_change_beyond_rounding(tmp_path, capsys):
    same = load("same_results")
    rng = np.random.default_rng(0)
    base = {"s/obs": rng.normal(size=(5, 2, 3)), "s/est": np.zeros((5, 2, 10))}
    np.savez(tmp_path / "a.npz", **base)
    rounding = {k: v * (1 + 1e-13) for k, v in base.items()}
    np.savez(tmp_path / "b.npz", **rounding)
    changed = dict(base, **{"s/obs": base["s/obs"] + 1e-6})
    np.savez(tmp_path / "c.npz", **changed)
    np.savez(tmp_path / "d.npz", **{"s/obs": base["s/obs"][:4], "s/est": base["s/est"]})
    a, b, c, d = (str(tmp_path / f"{x}.npz") for x in "abcd")
    assert same.main(["compare", a, b]) == 0
    assert same.main(["compare", a, c]) == 1
    assert same.main(["compare", a, d]) == 1  # a shape differs
    assert "DIFFERENT" in capsys.readouterr().out
    assert same.relative_difference(np.zeros(3), np.zeros(3)) == 0.0
    with pytest.raises(SystemExit):
        same.main(["compare", a, str(tmp_path / "missing.npz")])


def test_same_results_per_quantity_measure_scales_by_the_quantity_not_the_entry(tmp_path):
    """An estimate passing near zero: a rounding-level absolute change there is huge per entry
    but not per quantity; a change beyond rounding is flagged by both measures."""
    same = load("same_results")
    est = np.linspace(-0.003, 0.003, 5)[:, None] * np.ones((5, 10))
    est[2] = -3.7e-6  # within 1/1000 of the quantity's size of zero
    rounding = est + 1e-14
    changed = est * (1 + 1e-6)
    assert same.relative_difference(est, rounding) > 1e-9
    assert same.quantity_difference(est, rounding) < 1e-10
    assert same.quantity_difference(est, changed) > 1e-7
    assert same.quantity_difference(np.zeros((3, 2)), np.zeros((3, 2))) == 0.0
    # Each quantity (last axis) has its own scale: a large one does not hide a small one's change.
    two = np.stack([np.full(4, 1e3), np.full(4, 1e-3)], axis=-1)
    moved = two.copy()
    moved[0, 1] += 1e-9
    assert same.quantity_difference(two, moved) == pytest.approx(1e-9 / (1e-3 + 1e-9))
    for name, arrays in (("a", est), ("b", rounding), ("c", changed)):
        np.savez(tmp_path / f"{name}.npz", **{"s/est": arrays})
    a, b, c = (str(tmp_path / f"{x}.npz") for x in "abc")
    assert same.main(["compare", a, b, "--measure", "element", "--rtol", "1e-9"]) == 1
    assert same.main(["compare", a, b]) == 0  # the defaults: per quantity, 1e-10
    assert same.main(["compare", a, c]) == 1


def test_same_results_open_loop_keeps_the_estimates_out_of_the_physics(monkeypatch):
    """Open loop: a change in the estimator moves the estimates but not one bit of the flight;
    closed loop (the default), the same change moves the flight too."""
    same = load("same_results")
    args = (1, "figure8_yaw", 3, 310)  # the first update at step 249; state() at 250, 300
    base = {loop: same.record_scenario(*args, open_loop=loop) for loop in (False, True)}
    original = UKF.update_linear

    def noisier(self, z, A, b, R):
        return original(self, z, A, b, 4.0 * R)

    monkeypatch.setattr(UKF, "update_linear", noisier)
    changed = {loop: same.record_scenario(*args, open_loop=loop) for loop in (False, True)}
    for loop in (False, True):
        assert same.relative_difference(base[loop]["est"], changed[loop]["est"]) > 1e-6
    assert np.array_equal(base[True]["state"], changed[True]["state"])
    assert not np.array_equal(base[False]["state"], changed[False]["state"])


def test_same_results_replayed_actions_take_the_controller_out(monkeypatch, tmp_path):
    """A replay of a recording's actions flies it again bit for bit; a change in the controller
    moves a live recording but not the replay; bad replay requests are refused."""
    same = load("same_results")
    args = (1, "figure8_yaw", 3, 120)
    base = same.record_scenario(*args, open_loop=True)
    assert base["act"].shape[:2] == (120, 1) and base["state"].shape[0] == 3
    from astrocargo.agents.controllers import ObservationController

    original = ObservationController.predict

    def nudged(self, obs, *rest, **kw):
        actions, state = original(self, obs, *rest, **kw)
        return {a: 0.99 * u for a, u in actions.items()}, state

    monkeypatch.setattr(ObservationController, "predict", nudged)
    live = same.record_scenario(*args, open_loop=True)
    replay = same.record_scenario(*args, open_loop=True, actions=base["act"])
    assert not np.array_equal(live["act"], base["act"])
    assert not np.array_equal(live["state"], base["state"])
    for key, value in base.items():
        assert np.array_equal(replay[key], value), key
    with pytest.raises(ValueError, match="recorded robots"):
        same.record_scenario(2, "figure8_yaw", 3, 5, open_loop=True, actions=base["act"][:5])
    np.savez(tmp_path / "old.npz", **{"r1_yaw_open/obs": base["obs"]})
    out = str(tmp_path / "new.npz")
    old, missing = str(tmp_path / "old.npz"), str(tmp_path / "missing.npz")
    for argv in (
        ["record", out, "--actions", old],  # not open loop
        ["record", out, "--open-loop", "--actions", missing],
        ["record", out, "--open-loop", "--actions", old],  # no r1_yaw_open/act in it
    ):
        with pytest.raises(SystemExit):
            same.main(argv)
    assert not (tmp_path / "new.npz").exists()
