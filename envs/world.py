"""The MuJoCo world: an ISS module, one cargo bag and N Astrobees holding it.

The model is assembled with ``mujoco.MjSpec`` from MJCF files in ``assets/``: the module is the
root, the cargo bag is attached at the module centre, and robot ``i`` is attached with the prefix
``astrobee_i/`` at the pose that makes its gripper's ``grasp`` site coincide with the cargo's
``grasp_i`` site while its arm is deployed (tilt -pi/2, pan 0).

Cargo bags (``CARGO_BAGS``): the half CTB of ``cargo.xml`` has four handrails, one per side face,
and carries every team of up to four robots; the single CTB of ``cargo_single_ctb.xml`` has eight
(two on each long face 0.44 m apart, one on each end face, one on top, one underneath) and
carries teams of five to eight. ``World(n_robots)`` takes the smallest bag with a handrail per
robot, or the one named by ``cargo_bag``; ``cargo_size_m`` and ``uniform_cargo_inertia`` describe
the bag in use. Eight robots on the single CTB keep at least 0.086 m between any two of them and
0.13 m from the aisle's walls along ``figure8_yaw`` (assets/README.md gives the figures).

Grasp mechanism: a rigid grasp, built as the seed paper's tree rooted at the cargo. The cargo is
the only free body; robot i's kinematic chain is re-rooted at its gripper, which is fixed to the
cargo's handrail i, so the chain reads cargo -> gripper -> distal -(pan)-> proximal -(tilt)->
arm bay -> base. Joint angles keep their meaning (the reversed hinge sits at the same point with
the axis negated), so encoders, servos and the estimator's base-rooted model are unchanged. Slip is
zero by construction and the simulated physics is exactly the rigid sub-body model the estimator
uses. Welds were tried first and rejected: a soft weld between a 0.2 kg gripper and a 5 kg cargo
leaves relative accelerations of 1e-2 rad/s^2 (and far more under arm motion) at the grasp, so the
rigid model and the simulation disagree by several times the propulsion limits at an instant
(scratch measurement kept in the commit history). Contacts between the arm links and the cargo
are excluded (the fingers close around the handrail).

Release: a robot that lets go of the cargo leaves this tree, so the world is rebuilt without it
(``World.without_robots``) and the state of every remaining joint, actuator and the time are
copied over (``World.load_state``): the cargo and the robots still holding it continue exactly
where they were (same positions and velocities, so the same momentum), and the released robot,
with the momentum it carried (``World.momentum``), is no longer simulated. It is removed rather
than kept as a second free body: nobody commands it any more, it would drift through the module
into walls (a wall contact ends the episode) or into the cargo (a disturbance no estimator
models), and while it does not touch anything its presence changes nothing for the others.

``World.robot_model(i)`` reads robot i's known model (link masses, centres of mass, inertias, joint
axes, fixed transforms, IMU / thrust / grasp frames) from the compiled model, merging bodies without
joints into their parent: it is the estimator's single source of truth.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import mujoco
import numpy as np

from astrocargo.assets import ASSETS_DIR
from astrocargo.estimator.geometry import quat_to_mat
from astrocargo.estimator.inertia import (
    check_physical,
    mass_com_inertia_from_params,
    params_from_mass_com_inertia,
    transform_params,
)
from astrocargo.estimator.rne import LinkDescription, RobotDescription


@dataclass(frozen=True)
class CargoBag:
    """A cargo bag asset: its MJCF file in ``assets/`` and its handrails (sites ``grasp_0`` to
    ``grasp_{n_handrails - 1}``; robot i holds handrail i)."""

    name: str
    file: str
    n_handrails: int


# Smallest first: World picks the first bag with a handrail per robot unless told which. The half
# CTB stays the bag of every team of up to four (the README's results and benchmark figures were
# made with it); the single CTB carries five to eight (assets/README.md: layouts and sources).
CARGO_BAGS = (
    CargoBag("half_ctb", "cargo.xml", 4),
    CargoBag("single_ctb", "cargo_single_ctb.xml", 8),
)
MAX_ROBOTS = max(bag.n_handrails for bag in CARGO_BAGS)  # a handrail per robot
MAX_TIMESTEP_S = 0.016  # RK4 is checked up to one step per 62.5 Hz control period
ARM_DEPLOYED_RAD = (-np.pi / 2, 0.0)  # tilt, pan: arm straight aft (sources §5, docs/design.md)
THRUST_ACTUATORS = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
ARM_JOINTS = ("tilt", "pan")
ARM_LINK_BODIES = ("proximal", "distal", "gripper")
GRASP_BODY = "gripper"  # the robot body that holds the cargo
ROBOT_SENSORS = ("imu_accel", "imu_gyro", "base_pos", "base_quat", "tilt_pos", "pan_pos")


def _model_quat(rot: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation matrix for the model (MJCF frames, inertia axes),
    with MuJoCo's own sign convention (``mju_mat2Quat``): q and -q are one rotation, but the sign
    written into the model is the sign of the body quaternions ``state()`` reports."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rot, dtype=float).reshape(9))
    return quat


_JOINT_QPOS = {
    int(mujoco.mjtJoint.mjJNT_FREE): 7,
    int(mujoco.mjtJoint.mjJNT_BALL): 4,
    int(mujoco.mjtJoint.mjJNT_SLIDE): 1,
    int(mujoco.mjtJoint.mjJNT_HINGE): 1,
}
_JOINT_DOFS = {
    int(mujoco.mjtJoint.mjJNT_FREE): 6,
    int(mujoco.mjtJoint.mjJNT_BALL): 3,
    int(mujoco.mjtJoint.mjJNT_SLIDE): 1,
    int(mujoco.mjtJoint.mjJNT_HINGE): 1,
}


def _fmt(v: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in v)


def _robot_held_xml(robot_model: mujoco.MjModel) -> str:
    """astrobee.xml re-rooted at the gripper (see the module docstring).

    Every body keeps its own frame and contents (inertial, geoms, sites); only the nesting, the
    body poses relative to their new parents and the joints change. Poses come from the compiled
    forward model, so no number is re-typed.
    """
    root = ET.parse(ASSETS_DIR / "astrobee.xml").getroot()
    worldbody = root.find("worldbody")
    elems: dict[str, ET.Element] = {}
    parent_of: dict[str, str | None] = {}

    def walk(el: ET.Element, parent: str | None) -> None:
        elems[el.get("name")] = el
        parent_of[el.get("name")] = parent
        for child in el.findall("body"):
            walk(child, el.get("name"))

    for top in worldbody.findall("body"):
        walk(top, None)
    path = [GRASP_BODY]
    while parent_of[path[-1]] is not None:
        path.append(parent_of[path[-1]])
    if len(path) != len(elems):
        raise ValueError("every robot body must lie on the path from the base to the gripper")
    joints = {}
    for name in path:
        el = elems[name]
        hinge = [j for j in el.findall("joint") if j.get("type", "hinge") == "hinge"]
        joints[name] = hinge[0] if hinge else None
        for child in list(el):
            if child.tag in ("joint", "freejoint", "body"):
                el.remove(child)
        el.attrib.pop("pos", None)
        el.attrib.pop("quat", None)
        el.set("childclass", "astrobee")
    for child, parent in zip(path[:-1], path[1:], strict=True):
        b = robot_model.body(child).id
        rot_c = quat_to_mat(robot_model.body_quat[b])
        pos_c = robot_model.body_pos[b]
        pel = elems[parent]
        pel.set("pos", _fmt(-rot_c.T @ pos_c))
        pel.set("quat", _fmt(_model_quat(rot_c.T)))
        joint = joints[child]
        if joint is not None:
            jid = robot_model.joint(joint.get("name")).id
            if np.linalg.norm(robot_model.jnt_pos[jid]) > 1e-12:
                raise ValueError(f"joint {joint.get('name')} must sit at its body origin")
            joint.set("pos", _fmt(pos_c))
            joint.set("axis", _fmt(-rot_c @ robot_model.jnt_axis[jid]))
            pel.insert(0, joint)
        elems[child].append(pel)
    worldbody.clear()
    worldbody.append(elems[GRASP_BODY])
    return ET.tostring(root, encoding="unicode")


@dataclass(frozen=True)
class RobotHandles:
    """Indices of robot i's pieces in the compiled world model."""

    index: int
    prefix: str
    base_body: int
    arm_joints: tuple[int, ...]
    arm_qpos_adr: tuple[int, ...]
    arm_dof_adr: tuple[int, ...]
    thrust_actuators: tuple[int, ...]
    arm_actuators: tuple[int, ...]
    thrust_site: int
    imu_site: int
    grasp_site: int
    cargo_grasp_site: int
    link_bodies: tuple[int, ...]  # bodies of the arm (proximal, distal, gripper)
    robot_bodies: tuple[int, ...]  # every body of the robot
    robot_geoms: tuple[int, ...]
    sensor_adr: dict[str, int]


class World:
    """An ISS module with one cargo held by ``n_robots`` Astrobees.

    Args:
        n_robots: number of robots, 1 to ``MAX_ROBOTS``; robot i holds handrail i.
        timestep_s: physics step; ``None`` keeps the MJCF's 0.016 s.
        cargo_pos_m: initial position of the cargo centre in the module frame.
        holding: the robots (indices in 0..n_robots-1) that hold the cargo and are simulated;
            ``None``: all of them. ``robots`` lists their handles in increasing index (the
            handle's ``index`` is the robot's); the others are absent from the model.
        cargo_bag: name of the bag in ``CARGO_BAGS``; ``None``: the smallest with a handrail per
            robot (the half CTB for up to four robots, the single CTB for five to eight).
    """

    def __init__(
        self,
        n_robots: int = 2,
        timestep_s: float | None = None,
        cargo_pos_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        holding: tuple[int, ...] | list[int] | None = None,
        cargo_bag: str | None = None,
    ) -> None:
        if isinstance(n_robots, bool) or not isinstance(n_robots, int | np.integer):
            raise ValueError(f"n_robots must be an integer in 1..{MAX_ROBOTS}, got {n_robots!r}")
        if not 1 <= n_robots <= MAX_ROBOTS:
            raise ValueError(f"n_robots must be in 1..{MAX_ROBOTS}, got {n_robots}")
        self.cargo_bag = _choose_bag(int(n_robots), cargo_bag)
        if timestep_s is not None and not (
            np.isfinite(timestep_s) and 0 < timestep_s <= MAX_TIMESTEP_S
        ):
            raise ValueError(f"timestep_s must be in (0, {MAX_TIMESTEP_S}] s, got {timestep_s}")
        cargo_pos = np.asarray(cargo_pos_m, dtype=float)
        if cargo_pos.shape != (3,) or not np.all(np.isfinite(cargo_pos)):
            raise ValueError(f"cargo_pos_m must be 3 finite numbers, got {cargo_pos_m!r}")
        self.n_robots = int(n_robots)
        self.holding = self._check_holding(holding)
        self.cargo_pos = cargo_pos
        self.robot_asset_model = mujoco.MjModel.from_xml_path(str(ASSETS_DIR / "astrobee.xml"))
        # The spec is not kept: MjSpec does not pickle, and the compiled model is all we need
        # (a World, and the env holding it, can be deep-copied and sent to other processes).
        spec = self._build_spec(cargo_pos)
        if timestep_s is not None:
            spec.option.timestep = float(timestep_s)
        self.model = spec.compile()
        self.robots = tuple(self._handles(i) for i in self.holding)
        # Handrail i is on the cargo whether or not robot i holds it (known geometry).
        self.handrail_sites = tuple(
            self.model.site(f"cargo/grasp_{i}").id for i in range(self.n_robots)
        )
        # Commands are clipped to the propulsion limits (ctrlrange) by whoever issues them; the
        # actuation noise added afterwards (sensors.SensorSuite.actuate) is error of the delivered
        # wrench, not part of the command, so MuJoCo must not clip it: one-sided clipping of the
        # noise at saturation biases the delivered wrench (measured: +1.5 % cargo mass).
        for h in self.robots:
            self.model.actuator_ctrllimited[list(h.thrust_actuators)] = 0
        self.cargo_body = self.model.body("cargo/bag").id
        # The bag's outer size (x, y, z), m: its collision box.
        self.cargo_size_m = 2.0 * self.model.geom_size[self.model.geom("cargo/bag").id].copy()
        self.cargo_qpos_adr = int(self.model.jnt_qposadr[self.model.body_jntadr[self.cargo_body]])
        self.cargo_qvel_adr = int(self.model.jnt_dofadr[self.model.body_jntadr[self.cargo_body]])
        self.wall_geoms = tuple(
            g for g in range(self.model.ngeom) if self.model.geom_bodyid[g] == 0
        )
        self._set_grasp_keyframe()
        model = _read_robot_model(self.robot_asset_model)
        self._robot_models = (model,) * self.n_robots  # identical robots

    def _check_holding(self, holding: object) -> tuple[int, ...]:
        if holding is None:
            return tuple(range(self.n_robots))
        if not isinstance(holding, tuple | list):
            raise ValueError(f"holding must be None or a list of robot indices, got {holding!r}")
        for i in holding:
            if isinstance(i, bool) or not isinstance(i, int | np.integer):
                raise ValueError(f"holding: robot indices must be integers, got {i!r}")
            if not 0 <= i < self.n_robots:
                raise ValueError(
                    f"holding: robot indices must be in 0..{self.n_robots - 1}, got {i}"
                )
        if len(set(holding)) != len(holding):
            raise ValueError(f"holding names a robot twice: {holding!r}")
        return tuple(sorted(int(i) for i in holding))

    # ------------------------------------------------------------------ building
    def _build_spec(self, cargo_pos: np.ndarray) -> mujoco.MjSpec:
        spec = mujoco.MjSpec.from_file(str(ASSETS_DIR / "iss_module.xml"))
        cargo = mujoco.MjSpec.from_file(str(ASSETS_DIR / self.cargo_bag.file))
        cargo_grasp = self._site_poses(
            cargo.copy(), [f"grasp_{i}" for i in range(self.cargo_bag.n_handrails)]
        )
        spec.attach(cargo, prefix="cargo/", frame=spec.worldbody.add_frame(pos=cargo_pos))
        bag = spec.body("cargo/bag")
        # set_cargo moves the inertial frame at run time: never compile the bag as a "simple"
        # body (inertial frame on the body frame), which it would be with no robot attached.
        bag.simple = 0

        # Gripper pose in the cargo frame: its grasp site on the cargo's grasp_i site.
        m = self.robot_asset_model
        s = m.site("grasp").id
        if m.site_bodyid[s] != m.body(GRASP_BODY).id:
            raise ValueError(f"the grasp site must be on the {GRASP_BODY} body")
        rot_gs, pos_gs = quat_to_mat(m.site_quat[s]), m.site_pos[s]
        held_xml = _robot_held_xml(m)
        for i in self.holding:
            rot_cs, pos_cs = cargo_grasp[i]
            rot_cg = rot_cs @ rot_gs.T
            frame = bag.add_frame(pos=pos_cs - rot_cg @ pos_gs, quat=_model_quat(rot_cg))
            spec.attach(mujoco.MjSpec.from_string(held_xml), prefix=f"astrobee_{i}/", frame=frame)
            for link in ARM_LINK_BODIES:
                spec.add_exclude(bodyname1=f"astrobee_{i}/{link}", bodyname2="cargo/bag")
        return spec

    @staticmethod
    def _site_poses(spec: mujoco.MjSpec, names: list[str]) -> list[tuple[np.ndarray, np.ndarray]]:
        model = spec.compile()
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        out = []
        for name in names:
            s = model.site(name).id
            out.append((data.site_xmat[s].reshape(3, 3).copy(), data.site_xpos[s].copy()))
        return out

    def _handles(self, i: int) -> RobotHandles:
        m = self.model
        p = f"astrobee_{i}/"
        joints = tuple(m.joint(p + j).id for j in ARM_JOINTS)
        bodies = tuple(b for b in range(m.nbody) if m.body(b).name.startswith(p))
        return RobotHandles(
            index=i,
            prefix=p,
            base_body=m.body(p + "base").id,
            arm_joints=joints,
            arm_qpos_adr=tuple(int(m.jnt_qposadr[j]) for j in joints),
            arm_dof_adr=tuple(int(m.jnt_dofadr[j]) for j in joints),
            thrust_actuators=tuple(m.actuator(p + a).id for a in THRUST_ACTUATORS),
            arm_actuators=tuple(m.actuator(p + j).id for j in ARM_JOINTS),
            thrust_site=m.site(p + "thrust").id,
            imu_site=m.site(p + "imu").id,
            grasp_site=m.site(p + "grasp").id,
            cargo_grasp_site=m.site(f"cargo/grasp_{i}").id,
            link_bodies=tuple(m.body(p + b).id for b in ARM_LINK_BODIES),
            robot_bodies=bodies,
            robot_geoms=tuple(g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies),
            sensor_adr={n: int(m.sensor_adr[m.sensor(p + n).id]) for n in ROBOT_SENSORS},
        )

    def _set_grasp_keyframe(self) -> None:
        qpos = self.model.qpos0.copy()
        ctrl = np.zeros(self.model.nu)
        for h in self.robots:
            for adr, act, q in zip(h.arm_qpos_adr, h.arm_actuators, ARM_DEPLOYED_RAD, strict=True):
                qpos[adr] = q
                ctrl[act] = q
        self.qpos_grasp = qpos
        self.ctrl_grasp = ctrl

    # ------------------------------------------------------------------ state
    def make_data(self) -> mujoco.MjData:
        """A fresh ``MjData`` in the grasp configuration, at rest, after ``mj_forward``."""
        data = mujoco.MjData(self.model)
        self.reset_data(data)
        return data

    def reset_data(self, data: mujoco.MjData) -> None:
        """Put ``data`` in the grasp configuration at rest and run ``mj_forward``."""
        mujoco.mj_resetData(self.model, data)
        data.qpos[:] = self.qpos_grasp
        data.ctrl[:] = self.ctrl_grasp
        mujoco.mj_forward(self.model, data)

    # ------------------------------------------------------------------ release
    def handle(self, i: int) -> RobotHandles:
        """The handles of robot i, which must be holding the cargo in this world."""
        for h in self.robots:
            if h.index == i:
                return h
        raise ValueError(f"robot {i} is not in this world; holding: {self.holding}")

    def without_robots(self, released: tuple[int, ...] | list[int]) -> World:
        """This world rebuilt without the robots ``released`` (they let go of the cargo): same
        timestep, bag and cargo; load the state with ``load_state``."""
        for i in released:
            self.handle(i)
        world = World(
            self.n_robots,
            cargo_pos_m=tuple(self.cargo_pos),
            holding=tuple(i for i in self.holding if i not in released),
            cargo_bag=self.cargo_bag.name,
        )
        world.model.opt.timestep = self.model.opt.timestep
        b, nb = self.cargo_body, world.cargo_body
        for field in ("body_mass", "body_ipos", "body_inertia", "body_iquat"):
            getattr(world.model, field)[nb] = getattr(self.model, field)[b]
        mujoco.mj_setConst(world.model, mujoco.MjData(world.model))
        return world

    def layout_in(self, other: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where this world's qpos entries, qvel entries and bodies sit in ``other``'s (a world
        holding at least the same robots), matched by name: three index arrays (body 0, the
        module, maps to 0)."""
        m, o = self.model, other.model
        qpos, qvel = [], []
        for j in range(m.njnt):
            k = o.joint(m.joint(j).name).id  # every joint is named (cargo/root, astrobee_i/...)
            kind = int(m.jnt_type[j])
            qpos.extend(range(o.jnt_qposadr[k], o.jnt_qposadr[k] + _JOINT_QPOS[kind]))
            qvel.extend(range(o.jnt_dofadr[k], o.jnt_dofadr[k] + _JOINT_DOFS[kind]))
        bodies = [o.body(m.body(b).name).id for b in range(m.nbody)]
        return np.array(qpos, dtype=int), np.array(qvel, dtype=int), np.array(bodies, dtype=int)

    def load_state(self, source: World, source_data: mujoco.MjData, data: mujoco.MjData) -> None:
        """Copy into ``data`` the state of ``source_data`` (a state of world ``source``) for every
        joint and actuator present here, matched by name: time, positions, velocities, controls,
        activations and the solver's warm start; then ``mj_forward``. The bodies present in both
        worlds end with the same poses and velocities."""
        src, dst = source.model, self.model
        qpos, qvel, _ = self.layout_in(source)
        mujoco.mj_resetData(dst, data)
        data.time = source_data.time
        data.qpos[:] = source_data.qpos[qpos]
        data.qvel[:] = source_data.qvel[qvel]
        data.qacc_warmstart[:] = source_data.qacc_warmstart[qvel]
        for a in range(dst.nu):
            k = src.actuator(dst.actuator(a).name).id
            data.ctrl[a] = source_data.ctrl[k]
            if dst.actuator_actadr[a] >= 0:
                n = dst.actuator_actnum[a]
                aa, ab = dst.actuator_actadr[a], src.actuator_actadr[k]
                data.act[aa : aa + n] = source_data.act[ab : ab + n]
        mujoco.mj_forward(dst, data)

    def momentum(self, data: mujoco.MjData, bodies: tuple[int, ...] | None = None) -> np.ndarray:
        """Linear momentum (kg m/s) and angular momentum about the world origin (kg m^2/s), world
        axes, of ``bodies`` (default: every body but the world), (6,); ``data`` after
        ``mj_forward``."""
        m = self.model
        out = np.zeros(6)
        vel = np.zeros(6)
        for b in range(1, m.nbody) if bodies is None else bodies:
            mujoco.mj_objectVelocity(m, data, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)
            rot = data.ximat[b].reshape(3, 3)
            linear = m.body_mass[b] * vel[3:]
            out[:3] += linear
            out[3:] += rot @ (m.body_inertia[b] * (rot.T @ vel[:3]))
            out[3:] += np.cross(data.xipos[b], linear)
        return out

    # ------------------------------------------------------------------ cargo
    def uniform_cargo_inertia(self, mass_kg: float) -> np.ndarray:
        """Inertia (3, 3) about its centre of a uniform box of the bag's outer size and
        ``mass_kg``: the cargo a user who gives no inertia gets, matching the bag."""
        a, b, c = self.cargo_size_m**2
        return mass_kg / 12.0 * np.diag([b + c, a + c, a + b])

    def cargo_params(self) -> np.ndarray:
        """True cargo parameters pi (10,) in the cargo frame (origin at the bag's centre)."""
        b = self.cargo_body
        rot = quat_to_mat(self.model.body_iquat[b])
        inertia = rot @ np.diag(self.model.body_inertia[b]) @ rot.T
        return params_from_mass_com_inertia(
            self.model.body_mass[b], self.model.body_ipos[b].copy(), inertia
        )

    def cargo_params_in_grasp_frame(self, i: int, params: np.ndarray | None = None) -> np.ndarray:
        """True cargo parameters pi (10,) in robot i's grasp frame (what its estimator finds):
        ``params``, the cargo frame's (``cargo_params()``, computed when not given), moved into
        the frame of robot i's handrail site."""
        params = self.cargo_params() if params is None else params
        s = self.handrail_sites[i]
        rot = quat_to_mat(self.model.site_quat[s])
        return transform_params(params, rot.T, -rot.T @ self.model.site_pos[s])

    def relative_grasp(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose (rotation, position) of robot j's grasp frame in robot i's: the grasp layout on
        the cargo's handrails, known geometry."""
        poses = []
        for k in (i, j):
            s = self.handrail_sites[k]
            poses.append((quat_to_mat(self.model.site_quat[s]), self.model.site_pos[s]))
        (rot_i, pos_i), (rot_j, pos_j) = poses
        return rot_i.T @ rot_j, rot_i.T @ (pos_j - pos_i)

    def set_cargo(
        self,
        mass_kg: float,
        com_m: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
        inertia_com: np.ndarray | None = None,
    ) -> None:  # inertia_com is required; None only so the error message can say so
        """Change the cargo's mass, centre of mass (cargo frame, m) and full inertia tensor about
        the centre of mass (cargo frame axes, kg m^2) in place, without recompiling.

        Raises ``ValueError`` naming the violated condition for non-physical values (m <= 0,
        inertia not positive definite, triangle inequality broken). Call ``mj_forward`` (or the
        env's reset) afterwards so derived quantities are refreshed.
        """
        mass_arr = np.asarray(mass_kg, dtype=float)
        if mass_arr.shape != ():
            raise ValueError(f"mass_kg must be a scalar, got shape {mass_arr.shape}")
        mass = float(mass_arr)
        com = np.asarray(com_m, dtype=float)
        if com.shape != (3,):
            raise ValueError(f"com_m must have shape (3,), got {com.shape}")
        if inertia_com is None:
            raise ValueError("inertia_com (3x3 tensor about the centre of mass) is required")
        inertia = np.asarray(inertia_com, dtype=float)
        if inertia.shape != (3, 3):
            raise ValueError(f"inertia_com must have shape (3, 3), got {inertia.shape}")
        if not np.allclose(inertia, inertia.T, atol=1e-12):
            raise ValueError("inertia_com must be symmetric")
        if not (np.isfinite(mass) and np.all(np.isfinite(com)) and np.all(np.isfinite(inertia))):
            raise ValueError("cargo mass, centre of mass and inertia must be finite")
        # Also rejects what MuJoCo's compiler would (mass, positive definiteness, triangle).
        check_physical(params_from_mass_com_inertia(mass, com, inertia))
        moments, axes = np.linalg.eigh(inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 0] *= -1
        b = self.cargo_body
        self.model.body_mass[b] = mass
        self.model.body_ipos[b] = com
        self.model.body_inertia[b] = moments
        self.model.body_iquat[b] = _model_quat(axes)
        # Keep mj_setConst-derived quantities consistent (body_subtreemass is used by sensors).
        # Its scratch data is kept and reset (a fresh MjData is a reset one; the constants are
        # the same, bit for bit; allocating one was most of this call's time).
        if getattr(self, "_const_data", None) is None:
            self._const_data = mujoco.MjData(self.model)
        mujoco.mj_resetData(self.model, self._const_data)
        mujoco.mj_setConst(self.model, self._const_data)

    # ------------------------------------------------------------------ known robot model
    def robot_model(self, i: int) -> RobotDescription:
        """Robot i's known model, read from the compiled model (see ``estimator.rne``)."""
        if not 0 <= i < self.n_robots:
            raise ValueError(f"robot index must be in 0..{self.n_robots - 1}, got {i}")
        return self._robot_models[i]


def _choose_bag(n_robots: int, name: str | None) -> CargoBag:
    """The bag named ``name``, or the smallest with a handrail per robot."""
    if name is None:
        return next(bag for bag in CARGO_BAGS if bag.n_handrails >= n_robots)
    bags = {bag.name: bag for bag in CARGO_BAGS}
    if not isinstance(name, str) or name not in bags:
        raise ValueError(f"cargo_bag must be None or one of {list(bags)}, got {name!r}")
    if bags[name].n_handrails < n_robots:
        raise ValueError(
            f"cargo_bag {name!r} has {bags[name].n_handrails} handrails, fewer than n_robots "
            f"= {n_robots}"
        )
    return bags[name]


def _body_params(m: mujoco.MjModel, b: int) -> np.ndarray:
    """Inertial parameters pi of body b in its own frame."""
    rot = quat_to_mat(m.body_iquat[b])
    inertia = rot @ np.diag(m.body_inertia[b]) @ rot.T
    return params_from_mass_com_inertia(m.body_mass[b], m.body_ipos[b].copy(), inertia)


def _local_pose(m: mujoco.MjModel, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Body b's frame in its parent's: rotation, position."""
    return quat_to_mat(m.body_quat[b]), m.body_pos[b].copy()


def _hinge_link(m: mujoco.MjModel, b: int, parent_link: int, pose_in_parent: tuple) -> dict:
    """The link of body b, which has one hinge at its origin, in its parent link's frame."""
    j = m.body_jntadr[b]
    if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
        raise ValueError(f"body {m.body(b).name}: only hinge joints supported")
    if np.linalg.norm(m.jnt_pos[j]) > 1e-12:
        raise ValueError(f"joint {m.joint(j).name} must sit at its body origin")
    prot, ppos = pose_in_parent
    rot, pos = _local_pose(m, b)
    return dict(
        name=m.body(b).name,
        parent=parent_link,
        joint_axis=m.jnt_axis[j].copy(),
        rot_in_parent=prot @ rot,
        pos_in_parent=prot @ pos + ppos,
    )


def _robot_links(
    m: mujoco.MjModel, base_body: int, robot_bodies: tuple[int, ...]
) -> tuple[list[LinkDescription], dict[int, int], dict[int, tuple]]:
    """The robot's links (the base, then one per hinged body; bodies without joints merge into
    their parent link, their pose relative to it accumulated through the tree), with the link
    of each body and each body's pose in its link."""
    base = dict(name="base", parent=-1, joint_axis=None, rot_in_parent=np.eye(3))
    base["pos_in_parent"] = np.zeros(3)
    link_of: dict[int, int] = {}
    pose_in_link: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    params: list[np.ndarray] = []
    links: list[dict] = []
    for b in robot_bodies:  # bodies are numbered parent before child
        njnt, parent = m.body_jntnum[b], m.body_parentid[b]
        if b == base_body or njnt == 1:
            links.append(
                base if b == base_body else _hinge_link(m, b, link_of[parent], pose_in_link[parent])
            )
            link_of[b] = len(links) - 1
            pose_in_link[b] = (np.eye(3), np.zeros(3))
            params.append(_body_params(m, b))
        elif njnt == 0:
            prot, ppos = pose_in_link[parent]
            rot, pos = _local_pose(m, b)
            link_of[b] = link_of[parent]
            pose_in_link[b] = (prot @ rot, prot @ pos + ppos)
            params[link_of[b]] = params[link_of[b]] + transform_params(
                _body_params(m, b), *pose_in_link[b]
            )
        else:
            raise ValueError(f"body {m.body(b).name}: at most one joint per arm body")
    descriptions = []
    for link, pi in zip(links, params, strict=True):
        mass, com, inertia = mass_com_inertia_from_params(pi)
        descriptions.append(LinkDescription(mass=float(mass), com=com, inertia_com=inertia, **link))
    return descriptions, link_of, pose_in_link


def _read_robot_model(m: mujoco.MjModel) -> RobotDescription:
    """Read the known model of a robot from the compiled (base-rooted) astrobee.xml."""
    base_body = m.body("base").id
    robot_bodies = tuple(b for b in range(m.nbody) if m.body_rootid[b] == base_body)
    links, link_of, pose_in_link = _robot_links(m, base_body, robot_bodies)

    def site_in_link(s: int) -> tuple[int, np.ndarray, np.ndarray]:
        b = m.site_bodyid[s]
        prot, ppos = pose_in_link[b]
        return link_of[b], prot @ quat_to_mat(m.site_quat[s]), prot @ m.site_pos[s] + ppos

    imu_link, imu_rot, imu_pos = site_in_link(m.site("imu").id)
    thrust_link, thrust_rot, thrust_pos = site_in_link(m.site("thrust").id)
    grasp_link, grasp_rot, grasp_pos = site_in_link(m.site("grasp").id)
    if imu_link != 0 or thrust_link != 0:
        raise ValueError("the IMU and thrust sites must be on the base")
    thrust_actuators = [m.actuator(a).id for a in THRUST_ACTUATORS]
    arm_joints = [m.joint(j).id for j in ARM_JOINTS]
    thrust_gear = np.array([m.actuator_gear[a] for a in thrust_actuators])
    if not np.allclose(thrust_gear, np.eye(6)):
        raise ValueError("thrust actuators must be the six unit wrench directions")
    return RobotDescription(
        links=tuple(links),
        imu_rot=imu_rot,
        imu_pos=imu_pos,
        thrust_rot=thrust_rot,
        thrust_pos=thrust_pos,
        grasp_link=grasp_link,
        grasp_rot=grasp_rot,
        grasp_pos=grasp_pos,
        joint_range=np.array([m.jnt_range[j] for j in arm_joints]),
        thrust_limit=np.array([m.actuator_ctrlrange[a][1] for a in thrust_actuators]),
        servo_gain=np.array([m.actuator(name).gainprm[0] for name in ARM_JOINTS]),
    )
