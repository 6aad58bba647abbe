"""Headline demo: two Astrobees carry an unknown cargo and estimate its inertia in real time.

The same team, cargo, noise (`nominal`) and seed fly 90 s twice: the paper's scenario
(`figure8_yaw`: figure-eight, yaw ramp with a sudden turn at 40 s, arm pan ramp) and the team's
designed excitation (`excite`, agents/excitation_design.py: motion optimised for what the estimator
learns, within the robots' thrust, the servo and the walls), each driven by the cooperative
controller from the robots' observations and their own live estimates. Prints a table of final
errors and mass convergence times per robot and run, and saves one figure with the two runs side
by side (a column each, a row per parameter, like the paper's Fig. 3: the estimate with its
2-sigma band against the truth over time), so that one picture shows what the seed's trajectory
cannot reveal and what designed excitation does. Optionally an animated GIF of the `--trajectory`
run.

    MUJOCO_GL=egl .venv/bin/python scripts/demo.py                 # the defaults above
    .venv/bin/python scripts/demo.py --compare none --trajectory figure8_tumble --duration 60 \
        --video out/demo.gif                                       # one run only
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: see estimator/ukf.py

import numpy as np  # noqa: E402

os.environ.setdefault("MUJOCO_GL", "egl")

from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts/cli.py
from cli import (  # noqa: E402
    Formatter,
    check_trajectory,
    nonnegative_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
    trajectory,
)

from astrocargo.agents.controllers import ObservationController  # noqa: E402
from astrocargo.envs import astrobee_cargo_v0  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402
from astrocargo.estimator.baselines import convergence_time  # noqa: E402
from astrocargo.estimator.inertia import (  # noqa: E402
    inertia_to_vec,
    mass_com_inertia_from_params,
)

LABELS = ("m [kg]", "c_x [m]", "c_y [m]", "c_z [m]", "I_xx", "I_yy", "I_zz", "I_xy", "I_xz", "I_yz")
MASS_TOL = 0.02  # convergence: mass error stays within 2 %
CONTROL_HZ = 62.5  # the env's default control rate (Astrobee's GNC rate)


def physical(pi: np.ndarray) -> np.ndarray:
    """[m, c, I about the centre of mass (xx, yy, zz, xy, xz, yz)] of standard parameters."""
    mass, com, inertia = mass_com_inertia_from_params(pi)
    return np.concatenate(([mass], com, inertia_to_vec(inertia)))


def run(args: argparse.Namespace, trajectory: str, video: bool = False) -> dict:
    """Fly ``trajectory`` with the team, cargo, noise and seed of ``args``: the results (final
    errors, convergence, tracking) and, under "series", robot 0's estimate over time."""
    env = astrobee_cargo_v0.parallel_env(
        n_robots=args.robots,
        trajectory=trajectory,
        noise=args.noise,
        max_cycles=control_steps(args.duration),
        render_mode="rgb_array" if video else None,
    )
    obs, _ = env.reset(seed=args.seed)
    controller = ObservationController.for_env(env, args.cargo_model)
    sim = env.sim
    truth = [physical(p) for p in sim.true_params_grasp]
    times, means, stds, track, frames = [], [], [], [], []
    start = time.perf_counter()
    step = 0
    with tqdm(total=env.max_cycles, desc="simulating", unit="step") as bar:
        while env.agents:
            actions, _ = controller.predict(obs)
            obs, _, _, truncations, infos = env.step(actions)
            times.append(sim.data.time)
            estimates = [est.physical_estimate() for est in sim.estimators]
            means.append([m for m, _ in estimates])
            stds.append([s for _, s in estimates])
            track.append(sim.tracking_error())
            if video and step % args.video_every == 0:
                first = infos[env.possible_agents[0]]
                caption = (
                    f"t = {sim.data.time:5.1f} s   {env.possible_agents[0]}: mass error "
                    f"{first['mass_rel_err']:.1%}, CoM error {first['com_err_m'] * 1e3:.1f} mm"
                )
                frames.append(with_caption(env.render(), caption))
            step += 1
            bar.update()
    wall = time.perf_counter() - start
    reason = next(iter(infos.values())).get("termination_reason")
    times, means, stds, track = map(np.asarray, (times, means, stds, track))
    results = {
        "trajectory": trajectory,
        "seed": args.seed,
        "args": vars(args),
        "wall_s": wall,
        "sim_s": float(times[-1]),
        "termination_reason": reason,
        # None: the episode ran to its time limit (truncated), else the termination's reason.
        "end": "time limit" if reason is None and any(truncations.values()) else reason,
        "agents": {},
    }
    for i, agent in enumerate(env.possible_agents):
        info = infos[agent]
        mass_err = np.abs(means[:, i, 0] - truth[i][0]) / truth[i][0]
        results["agents"][agent] = {
            "mass_rel_err": info["mass_rel_err"],
            "com_err_m": info["com_err_m"],
            "principal_rel_err": [float(x) for x in info["principal_rel_err"]],
            "mass_convergence_s": convergence_time(times, mass_err, MASS_TOL),
            "counters": info["estimator"],
        }
    results["tracking"] = {
        "mean_pos_err_m": float(track[len(track) // 6 :, 0].mean()),
        "mean_att_err_deg": float(np.degrees(track[len(track) // 6 :, 1].mean())),
    }
    if frames:
        save_gif(frames, Path(args.video), fps=CONTROL_HZ / args.video_every)
    env.close()
    results["series"] = (times, means[:, 0], stds[:, 0], truth[0])
    return results


# Figure: the y-limits hold the estimate, its band and the truth from ZOOM_AFTER of the run on
# (the prior's band of the first seconds would hide the convergence); a parameter whose reported
# spread ends above UNREVEALED_STD_FRACTION of the prior's is one the trajectory cannot reveal.
ZOOM_AFTER = 0.2
UNREVEALED_STD_FRACTION = 0.5


def zoomed_limits(
    times: np.ndarray, mean: np.ndarray, std: np.ndarray, truth: float, revealed: bool
) -> tuple[float, float]:
    """y-limits holding the truth and, after ZOOM_AFTER of the run, the estimate and (for a
    revealed parameter) its 2-sigma band, with a 10 % margin."""
    late = times >= times[0] + ZOOM_AFTER * (times[-1] - times[0])
    values = [mean[late], [truth]]
    if revealed:
        values += [mean[late] - 2 * std[late], mean[late] + 2 * std[late]]
    lo, hi = float(np.min(np.concatenate(values))), float(np.max(np.concatenate(values)))
    margin = 0.1 * (hi - lo) or 0.05 * max(abs(truth), 1e-3)
    return lo - margin, hi + margin


def plot(runs: list[dict], args, path: Path) -> None:
    """Robot 0's estimate of each parameter (rows) with its 2-sigma band against the truth over
    time, one column per run (side by side, the same y-limits in a row)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_runs = len(runs)
    fig, axes = plt.subplots(
        len(LABELS), n_runs, figsize=(6.5 * n_runs + 1, 19), sharex=True, squeeze=False
    )
    limits = []
    for k in range(len(LABELS)):
        lows, highs = [], []
        for r in runs:
            times, mean, std, truth = r["series"]
            revealed = std[-1, k] / std[0, k] <= UNREVEALED_STD_FRACTION
            lo, hi = zoomed_limits(times, mean[:, k], std[:, k], truth[k], revealed)
            lows.append(lo if revealed else lo - 0.35 * (hi - lo))  # room for the note
            highs.append(hi)
        limits.append((min(lows), max(highs)))
    for col, r in enumerate(runs):
        times, mean, std, truth = r["series"]
        for k in range(len(LABELS)):
            ax = axes[k, col]
            spread = std[-1, k] / std[0, k]  # reported spread at the end over the prior's
            revealed = spread <= UNREVEALED_STD_FRACTION
            ax.fill_between(
                times,
                mean[:, k] - 2 * std[:, k],
                mean[:, k] + 2 * std[:, k],
                color="tab:blue",
                alpha=0.25,
                lw=0,
                label="estimate +- 2 sigma",
            )
            ax.plot(times, mean[:, k], color="tab:blue", lw=1.2, label="estimate")
            ax.axhline(truth[k], color="k", ls="--", lw=1, label="truth")
            ax.set_ylim(*limits[k])
            note = "revealed" if revealed else "NOT revealed"
            ax.text(
                0.99,
                0.04,
                f"{note}: spread {spread:.0%} of the prior's",
                transform=ax.transAxes,
                ha="right",
                va="bottom",
                fontsize=7.5,
                color="0.2" if revealed else "tab:red",
                bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.85, "lw": 0},
            )
            ax.ticklabel_format(axis="y", style="plain", useOffset=False)
            if col == 0:
                ax.set_ylabel(LABELS[k] if k < 4 else LABELS[k] + " [kg m^2]", fontsize=9)
        errs = r["agents"][next(iter(r["agents"]))]
        axes[0, col].set_title(
            f"{r['trajectory']}: mass {errs['mass_rel_err']:.1%}, CoM "
            f"{errs['com_err_m'] * 1e3:.1f} mm, principal moments "
            + " / ".join(f"{x:.0%}" for x in errs["principal_rel_err"])
            + f" at {r['sim_s']:.0f} s",
            fontsize=10,
        )
        axes[-1, col].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8, loc="upper right")
    fig.suptitle(
        f"astrobee_0's estimate of the cargo (grasp frame; inertia about the centre of mass) - "
        f"{args.robots} robots, {args.noise} noise, seed {args.seed}, the same cargo\n"
        f"'NOT revealed': reported spread still above {UNREVEALED_STD_FRACTION:.0%} of the "
        f"prior's at the end; y-limits: the estimates, bands and truth after "
        f"{ZOOM_AFTER:.0%} of the run",
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.965))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def with_caption(frame: np.ndarray, text: str) -> np.ndarray:
    """The frame with ``text`` on a dark band along its top edge."""
    from PIL import Image, ImageDraw, ImageFont

    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default(size=max(12, image.height // 28))
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    pad = 6
    draw.rectangle((0, 0, image.width, bottom - top + 2 * pad), fill=(0, 0, 0))
    draw.text((pad, pad - top), text, fill=(255, 255, 255), font=font)
    return np.asarray(image)


def save_gif(frames: list[np.ndarray], path: Path, fps: float) -> None:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


def print_table(results: dict) -> None:
    print(
        f"\n{results['trajectory']}: final estimates after {results['sim_s']:.1f} s "
        f"(wall {results['wall_s']:.1f} s, "
        f"real-time factor {results['sim_s'] / results['wall_s']:.1f}); "
        f"end: {results['end']}"
    )
    header = f"{'agent':<12}{'mass err':>10}{'CoM err':>10}{'principal moment errs':>26}"
    print(header + f"{'mass conv.':>12}{'updates':>9}{'skipped':>9}")
    for agent, r in results["agents"].items():
        conv = r["mass_convergence_s"]
        principal = " ".join(f"{x:6.1%}" for x in r["principal_rel_err"])
        skipped = sum(v for k, v in r["counters"].items() if k.startswith("skipped"))
        print(
            f"{agent:<12}{r['mass_rel_err']:>10.2%}{r['com_err_m'] * 1e3:>8.1f}mm"
            f"{principal:>26}{'never' if conv is None else f'{conv:.1f} s':>12}"
            f"{r['counters']['updates']:>9}{skipped:>9}"
        )
    t = results["tracking"]
    print(
        f"cargo tracking after the first sixth: {t['mean_pos_err_m'] * 100:.2f} cm, "
        f"{t['mean_att_err_deg']:.2f} deg (mean)"
    )


def control_steps(duration_s: float) -> int:
    """Control steps of an episode of ``duration_s`` simulated seconds."""
    return int(round(duration_s * CONTROL_HZ))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    parser.add_argument("--robots", type=int, default=2, help=f"1..{MAX_ROBOTS}")
    parser.add_argument(
        "--trajectory",
        type=trajectory,
        default="excite",
        help="figure8_yaw, figure8_tumble, hover, excite (the team's designed excitation) or a "
        "design JSON file",
    )
    parser.add_argument(
        "--compare",
        type=lambda text: text if text == "none" else trajectory(text),
        default="figure8_yaw",
        help="the trajectory flown first, beside --trajectory (the same team, cargo, noise and "
        "seed); none: fly --trajectory only",
    )
    parser.add_argument("--noise", default="nominal", choices=sorted(NOISE_PROFILES))
    parser.add_argument("--duration", type=positive_float, default=90.0, help="simulated seconds")
    parser.add_argument("--seed", type=nonnegative_int, default=0)
    parser.add_argument(
        "--cargo-model",
        default="estimate",
        choices=("estimate", "none", "truth"),
        help="cargo model the controller uses",
    )
    parser.add_argument("--out-dir", default="out/demo", help="folder of the figure and results")
    parser.add_argument(
        "--video", default=None, metavar="GIF", help="also write an animated GIF to this path"
    )
    parser.add_argument(
        "--video-every", type=positive_int, default=8, help="control steps per frame"
    )
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked, with its output folders created: every error is the parser's,
    before anything runs."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be in 1..{MAX_ROBOTS}, got {args.robots}")
    check_trajectory(parser, args.trajectory, args.robots)
    if args.compare != "none":
        check_trajectory(parser, args.compare, args.robots)
    if control_steps(args.duration) < 1:
        parser.error(
            f"--duration must be at least one control period ({1 / CONTROL_HZ} s), "
            f"got {args.duration}"
        )
    output_dir(parser, Path(args.out_dir), "--out-dir")
    if args.video is not None:
        output_file(parser, Path(args.video), "--video", suffix=".gif")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    print(f"seed {args.seed}")
    flown = ([] if args.compare == "none" else [args.compare]) + [args.trajectory]
    # The GIF shows the last run (--trajectory).
    last = len(flown) - 1
    runs = [run(args, traj, bool(args.video) and k == last) for k, traj in enumerate(flown)]
    out = Path(args.out_dir)
    plot(runs, args, out / "estimates.png")
    for r in runs:
        print_table(r)
    results = {r["trajectory"]: {k: v for k, v in r.items() if k != "series"} for r in runs}
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    print(
        f"figure: {Path(args.out_dir) / 'estimates.png'}; "
        f"results: {Path(args.out_dir) / 'results.json'}"
        + (f"; video: {args.video}" if args.video else "")
    )


if __name__ == "__main__":
    main()
