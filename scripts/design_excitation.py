"""Design an excitation trajectory for information (agents.excitation_design); write it as JSON.

The design cargo defaults to a 5 kg uniform bag of the team's cargo bag (centre of mass at its
centre); the noise model is the env's estimator settings of ``--noise``. Prints the predicted
Cramer-Rao bounds (1 sigma) of mass, centre of mass and principal moments and which constraint
binds.

    python scripts/design_excitation.py --robots 2 --duration 90 \\
        --out agents/designs/excite_2robots.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from astrocargo.agents.excitation import ExcitationDesign  # noqa: E402
from astrocargo.agents.excitation_design import (  # noqa: E402
    DesignSettings,
    ExcitationDesigner,
    Limits,
    model_for_world,
)
from astrocargo.agents.trajectories import Trajectory  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES, estimator_noise_kwargs, noise_profile  # noqa: E402
from astrocargo.envs.world import World  # noqa: E402
from astrocargo.estimator.inertia import params_from_mass_com_inertia  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=2)
    p.add_argument("--duration", type=float, default=90.0, help="flight, s")
    p.add_argument("--harmonics", type=int, default=DesignSettings.n_harmonics)
    p.add_argument("--period", type=float, default=None, help="base period, s (duration / 2)")
    p.add_argument("--ramp", type=float, default=DesignSettings.ramp_s, help="window ramps, s")
    p.add_argument("--starts", type=int, default=DesignSettings.starts)
    p.add_argument("--maxiter", type=int, default=DesignSettings.maxiter)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise", choices=sorted(NOISE_PROFILES), default="nominal")
    p.add_argument("--cargo-mass", type=float, default=5.0, help="design cargo, kg")
    p.add_argument("--thrust-margin", type=float, default=Limits.thrust_margin)
    p.add_argument("--clearance", type=float, default=Limits.clearance_m, help="m")
    p.add_argument("--no-pan", action="store_true", help="keep the arms deployed")
    p.add_argument(
        "--rescale",
        default=None,
        metavar="DESIGN",
        help="no search: scale this design's cargo motion by --scale and describe it",
    )
    p.add_argument("--scale", type=float, default=1.0, help="with --rescale, in (0, 1]")
    p.add_argument(
        "--relative-to",
        choices=Trajectory.NAMES,
        default=None,
        help="score the bounds against this trajectory's predicted bounds (maximise the worst "
        "improvement over it) instead of the issue's targets",
    )
    p.add_argument("--out", default=None, help="JSON (default excite_<N>robots.json)")
    args = p.parse_args(argv)

    print(f"seed {args.seed}")
    world = World(args.robots)
    cargo = params_from_mass_com_inertia(
        args.cargo_mass, np.zeros(3), world.uniform_cargo_inertia(args.cargo_mass)
    )
    limits = Limits(thrust_margin=args.thrust_margin, clearance_m=args.clearance)
    model = model_for_world(
        world, cargo, estimator_noise_kwargs(noise_profile(args.noise)), limits=limits
    )
    settings = dict(
        duration_s=args.duration,
        n_harmonics=args.harmonics,
        period_s=args.period,
        ramp_s=args.ramp,
        starts=args.starts,
        seed=args.seed,
        maxiter=args.maxiter,
        pan=not args.no_pan,
    )
    # The figure-eight tumble's predicted bounds on the designer's own grid (the yardstick).
    tumble = ExcitationDesigner(model, DesignSettings(**settings)).reference_bounds(
        Trajectory(args.relative_to or "figure8_tumble")
    )
    if args.relative_to:
        settings["targets"] = {k: tumble[k] for k in ("principal_rel", "mass_rel", "com_m")}
    start = time.perf_counter()
    designer = ExcitationDesigner(model, DesignSettings(**settings))
    if args.rescale:
        old = ExcitationDesign.load(args.rescale).scaled(args.scale)
        design = designer.describe(old)
        design.info.update(
            {k: old.info[k] for k in ("scaled", "settings", "runtime_s") if k in old.info}
        )
    else:
        design = designer.run(verbose=True)
    info = design.info
    info["noise"] = args.noise
    info["reference_bounds"] = {"trajectory": args.relative_to or "figure8_tumble", **tumble}
    out = args.out or f"excite_{args.robots}robots.json"
    design.save(out)
    b = info["predicted_bounds"]
    print(
        f"designed in {time.perf_counter() - start:.0f} s; predicted bounds (1 sigma): principal "
        f"{', '.join(f'{100 * x:.2f}' for x in b['principal_rel'])} %, mass "
        f"{100 * b['mass_rel']:.2f} %, CoM {1e3 * b['com_m']:.2f} mm; binding: {info['binding']} "
        f"(worst normalised value {info['max_violation'][info['binding']]:+.3f}); peak thrust / "
        f"limit per axis {np.round(info['peak_thrust_ratio_per_axis'], 2).tolist()}\n"
        f"{info['reference_bounds']['trajectory']} on the same grid: principal "
        f"{', '.join(f'{100 * x:.2f}' for x in tumble['principal_rel'])} %, mass "
        f"{100 * tumble['mass_rel']:.2f} %, CoM {1e3 * tumble['com_m']:.2f} mm\nwritten {out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
