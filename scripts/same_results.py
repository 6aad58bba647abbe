"""Same results: record seeded scenarios of the env, and compare two recordings.

A change meant to keep results (a speed-up, a refactor) must leave the observations, rewards,
estimates and ``state()`` of seeded runs unchanged to rounding. Record on the version before
the change, record again after, compare:

    .venv/bin/python scripts/same_results.py record out/before.npz
    .venv/bin/python scripts/same_results.py record out/after.npz
    .venv/bin/python scripts/same_results.py compare out/before.npz out/after.npz

Scenarios: the scripted controller with live estimates (``ObservationController``, cargo model
"estimate") flying each trajectory under ``nominal`` noise from a fixed seed, 1, 2, 3 and 8
robots. ``compare`` prints the largest relative difference per array (both measures below) and
exits 1 when one exceeds ``--rtol`` (default 1e-10, per quantity) or the shapes differ.

Closed or open loop. By default the controller flies on the estimates, so the estimator's
rounding feeds back into the physics. ``record --open-loop`` flies the same scenarios with the
controller on the true cargo model (arrays named ``<scenario>_open/...``): the estimates no
longer steer the robots, and only the estimates and what is built from them can move.
Every recording keeps the actions it flew (``<scenario>/act``, (T, N, 8)). ``record --open-loop
--actions REF.npz`` flies REF's open-loop actions again instead of running the controller, so
the controller is out of the comparison too: a rounding-level change in the controller (its
arm motion is a central difference over 10 ms, which divides rounding by 1e-4) moves the flown
trajectory and with it every quantity by up to ~3e-10 per quantity, over the bound below. Judge
an estimator or env change on a replay of the reference's actions; judge a controller change by
``act`` in plain recordings, against the same controller with its inputs moved by one unit in
the last place.

Two measures (``--measure``). ``element``: |a - b| / max(|a|, |b|) per entry. It is large
wherever a quantity passes near zero: on r2_excite_open robot 1's I_xy estimate is -3.7e-6 kg m^2
at step 669 (its posterior std 5.7e-3), so one unit in the last place of every update's R moves
that entry by 8e-15 absolute, 2.2e-9 relative, while the other scenarios stay at 1e-11..1e-10.
``quantity`` (the default): |a - b| / the largest |value| of that quantity (the array's last
axis) in either run, one scale for all its entries. Against main's recordings, rounding (one unit
in the last place of every update's R or b, regrouped sums, other BLAS calls) gave at most 4e-12
open loop, and R scaled by (1 + 1e-9) at every update 3.5e-10..8e-10. So the defaults,
``--measure quantity --rtol 1e-10`` on open-loop recordings, tell rounding from a change of the
arithmetic on every scenario: that is the project's same-results rule. Closed loop the same
rounding reaches 3.3e-10 per quantity (3.7e-7 per entry), as much as that 1e-9 change of R, so
the closed loop tells only bit-equal arithmetic from the rest.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import cli  # noqa: E402

# (name, robots, trajectory, seed, control steps); state() every STATE_EVERY steps.
SCENARIOS = (
    ("r1_yaw", 1, "figure8_yaw", 11, 700),
    ("r2_tumble", 2, "figure8_tumble", 12, 1200),
    ("r2_excite", 2, "excite", 13, 900),
    ("r3_tumble", 3, "figure8_tumble", 14, 700),
    ("r8_yaw", 8, "figure8_yaw", 15, 400),
)
STATE_EVERY = 50


def record_scenario(
    n_robots: int,
    trajectory: str,
    seed: int,
    steps: int,
    open_loop: bool = False,
    actions: np.ndarray | None = None,
) -> dict:
    """One scenario's arrays: actions (T, N, act_dim), observations (T, N, obs_dim), rewards
    (T, N), estimates (T, N, 10) and ``state()`` every STATE_EVERY steps, agents in sorted
    order; ``open_loop``: the controller flies on the true cargo model instead of the
    estimates; ``actions`` (T, N, act_dim): flown instead of the controller's."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(
        n_robots=n_robots, noise="nominal", trajectory=trajectory, max_cycles=steps + 10
    )
    obs, _ = env.reset(seed=seed)
    if actions is None:
        controller = ObservationController.for_env(env, "truth" if open_loop else "estimate")
    else:
        steps = len(actions)  # the recording's steps (fewer where its episode ended early)
    out = {"act": [], "obs": [], "rew": [], "est": [], "state": []}
    for k in range(steps):
        agents = sorted(obs)
        if actions is None:
            acting, _ = controller.predict(obs)
        elif actions.shape[1] != len(agents):
            raise ValueError(f"step {k}: {actions.shape[1]} recorded robots, {len(agents)} acting")
        else:
            acting = dict(zip(agents, actions[k], strict=True))
        obs, rewards, _, _, infos = env.step(acting)
        if not obs:
            break
        out["act"].append(np.stack([acting[a] for a in agents]))
        agents = sorted(obs)
        out["obs"].append(np.stack([obs[a] for a in agents]))
        out["rew"].append(np.array([rewards[a] for a in agents]))
        out["est"].append(np.stack([infos[a].get("estimate", np.zeros(10)) for a in agents]))
        if k % STATE_EVERY == 0:
            out["state"].append(env.state())
    return {key: np.array(value) for key, value in out.items()}


def record(path: Path, open_loop: bool = False, actions_from: Path | None = None) -> None:
    """Fly every scenario and write its arrays; ``actions_from``: a recording whose open-loop
    actions are flown again (``open_loop`` required)."""
    if actions_from is not None and not open_loop:
        raise ValueError("replayed actions need --open-loop: the estimates would not steer")
    replay = np.load(actions_from) if actions_from is not None else None
    arrays = {}
    for name, n_robots, trajectory, seed, steps in SCENARIOS:
        name = f"{name}_open" if open_loop else name
        actions = None
        if replay is not None:
            if f"{name}/act" not in replay.files:
                raise ValueError(f"{actions_from} has no {name}/act: record it with this script")
            actions = replay[f"{name}/act"]
        scenario = record_scenario(n_robots, trajectory, seed, steps, open_loop, actions)
        for key, value in scenario.items():
            arrays[f"{name}/{key}"] = value
        print(f"{name}: {len(arrays[f'{name}/obs'])} steps", flush=True)
    np.savez_compressed(path, **arrays)
    print(f"wrote {path}")


def relative_difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / max(|a|, |b|) elementwise, with values below 1e-12 of the array's largest
    taken at that floor (so exact zeros on one side do not count as 100 %)."""
    scale = np.maximum(np.abs(a), np.abs(b))
    scale = np.maximum(scale, 1e-12 * max(1.0, float(np.abs(a).max(initial=0.0))))
    return float(np.max(np.abs(a - b) / scale, initial=0.0))


def quantity_difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / s_q over the entries of each quantity q (the last axis), s_q the largest
    |value| of q in a or b, with s_q below 1e-12 of the array's largest taken at that floor."""
    axes = tuple(range(a.ndim - 1))
    scale = np.maximum(np.abs(a).max(axis=axes, initial=0.0), np.abs(b).max(axis=axes, initial=0.0))
    scale = np.maximum(scale, 1e-12 * max(1.0, float(np.abs(a).max(initial=0.0))))
    return float(np.max(np.abs(a - b) / scale, initial=0.0))


MEASURES = {"element": relative_difference, "quantity": quantity_difference}


def compare(path_a: Path, path_b: Path, rtol: float, measure: str = "quantity") -> bool:
    a, b = np.load(path_a), np.load(path_b)
    same = set(a.files) == set(b.files)
    if not same:
        print(f"different arrays: only in A {sorted(set(a.files) - set(b.files))}, "
              f"only in B {sorted(set(b.files) - set(a.files))}")  # fmt: skip
    worst = 0.0
    for key in sorted(set(a.files) & set(b.files)):
        if a[key].shape != b[key].shape:
            print(f"{key:20s} shape {a[key].shape} vs {b[key].shape}")
            same = False
            continue
        rel = {name: f(a[key], b[key]) for name, f in MEASURES.items()}
        worst = max(worst, rel[measure])
        print(f"{key:20s} max relative difference {rel['element']:.3e}, "
              f"per quantity {rel['quantity']:.3e}")  # fmt: skip
    same = same and worst <= rtol
    print(f"worst {worst:.3e}: {'same results' if same else 'DIFFERENT'} "
          f"(rtol {rtol:g}, measure {measure})")  # fmt: skip
    return same


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=cli.Formatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="fly the scenarios and write their arrays (.npz)")
    rec.add_argument("out", type=Path, help="the .npz file to write")
    rec.add_argument(
        "--open-loop", action="store_true", help="the controller flies on the true cargo model"
    )
    rec.add_argument(
        "--actions", type=Path, default=None, metavar="REF.npz",
        help="with --open-loop: fly REF's recorded actions instead of the controller",
    )  # fmt: skip
    cmp_ = sub.add_parser("compare", help="compare two recordings")
    cmp_.add_argument("a", type=Path)
    cmp_.add_argument("b", type=Path)
    cmp_.add_argument("--rtol", type=cli.nonnegative_float, default=1e-10)
    cmp_.add_argument(
        "--measure", choices=sorted(MEASURES), default="quantity",
        help="judge per entry or per quantity (see the module docstring)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.command == "record":
        cli.output_file(parser, args.out, "out", suffix=".npz")
        if args.actions is not None and not args.actions.is_file():
            parser.error(f"{args.actions} is not a file")
        try:
            record(args.out, args.open_loop, args.actions)
        except ValueError as error:
            parser.error(str(error))
        return 0
    for path in (args.a, args.b):
        if not path.is_file():
            parser.error(f"{path} is not a file")
    return 0 if compare(args.a, args.b, args.rtol, args.measure) else 1


if __name__ == "__main__":
    sys.exit(main())
