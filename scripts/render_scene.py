"""Render the ISS module with N Astrobees holding the cargo bag to a PNG.

Headless: ``MUJOCO_GL`` defaults to ``egl`` (Mesa's EGL works without a GPU); set
``MUJOCO_GL=osmesa`` to use the software fallback. Exits with status 1 if the picture is blank.

Example::

    MUJOCO_GL=egl .venv/bin/python scripts/render_scene.py --robots 2 --out scene.png
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# The GL backend is chosen when mujoco is imported, so this must come first.
os.environ.setdefault("MUJOCO_GL", "egl")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts/cli.py
from cli import Formatter  # noqa: E402

from astrocargo.envs.world import MAX_ROBOTS, World  # noqa: E402

MODULE_CAMERAS = ("overview", "aisle", "top")  # fixed cameras in assets/iss_module.xml
FREE_CAMERA = "closeup"  # computed in this script, framed on the cargo and its robots
BLANK_STD_THRESHOLD = 2.0  # pixel standard deviation (0-255 scale) below which a picture is blank

# Free camera: looks at the cargo centre from above one robot's shoulder, far enough to hold
# every robot (robot centres are ~0.53 m from the cargo centre; ~0.32 m cubes).
CLOSEUP_DISTANCE_M = 2.1
CLOSEUP_AZIMUTH_DEG = 155.0
CLOSEUP_ELEVATION_DEG = -22.0

# Geom groups: 2 visual geoms, 3 collision boxes (the robots, cargo and module are drawn with
# their collision boxes), 4 sites (off: they would hide the grasp points in the handrails).
VISIBLE_GEOM_GROUPS = (0, 1, 2, 3)


def _closeup_camera(world: World, data: mujoco.MjData) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = data.xpos[world.cargo_body]
    cam.distance = CLOSEUP_DISTANCE_M
    cam.azimuth = CLOSEUP_AZIMUTH_DEG
    cam.elevation = CLOSEUP_ELEVATION_DEG
    return cam


def render(n_robots: int, width: int, height: int, camera: str) -> np.ndarray:
    """An (height, width, 3) uint8 picture of the world in its grasp configuration."""
    world = World(n_robots)
    data = world.make_data()
    scene_option = mujoco.MjvOption()
    scene_option.geomgroup[:] = 0
    for group in VISIBLE_GEOM_GROUPS:
        scene_option.geomgroup[group] = 1
    cam: str | mujoco.MjvCamera = _closeup_camera(world, data) if camera == FREE_CAMERA else camera
    with mujoco.Renderer(world.model, height=height, width=width) as renderer:
        renderer.update_scene(data, camera=cam, scene_option=scene_option)
        return renderer.render()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    parser.add_argument("--robots", type=int, default=2, help=f"1..{MAX_ROBOTS}")
    parser.add_argument("--out", type=Path, default=Path("scene.png"), help="PNG file to write")
    parser.add_argument("--width", type=int, default=960, help="pixels, at most 1280")
    parser.add_argument("--height", type=int, default=540, help="pixels, at most 720")
    parser.add_argument(
        "--camera",
        default=FREE_CAMERA,
        choices=(FREE_CAMERA, *MODULE_CAMERAS),
        help=f"'{FREE_CAMERA}' (free camera on the cargo) or a module camera",
    )
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be in 1..{MAX_ROBOTS}, got {args.robots}")
    if not (1 <= args.width <= 1280 and 1 <= args.height <= 720):
        parser.error("--width must be in 1..1280 and --height in 1..720 (offscreen buffer)")
    if args.out.suffix.lower() != ".png":
        parser.error(f"--out must end in .png, got {args.out}")

    pixels = render(args.robots, args.width, args.height, args.camera)
    std = float(pixels.std())
    if std < BLANK_STD_THRESHOLD:
        msg = f"error: blank picture (pixel std {std:.2f} < {BLANK_STD_THRESHOLD})"
        print(msg, file=sys.stderr)
        return 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    plt.imsave(args.out, pixels)
    print(
        f"wrote {args.out} ({args.width}x{args.height}, {args.robots} robots, camera "
        f"{args.camera}, MUJOCO_GL={os.environ['MUJOCO_GL']}, pixel std {std:.1f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
