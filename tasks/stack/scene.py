"""The stacking scene on MuJoCo: a table, a red and a blue 4 cm cube, a floating parallel-jaw gripper.

Units are metres, z up, the table top at z = 0. The gripper is a hand on three slide joints (x, y, z) with two
fingers on slide joints along x; position actuators with velocity feedback track the action, gravity compensated,
so an action is a target: ``[x, y, z, opening]``, the point midway between the finger pads and the gap between
them. No yaw: the goal compares positions only and closing the jaws squares a cube up against them (a cube's yaw
is drawn in [-45, 45] degrees, all its orientations up to symmetry), so a fifth action entry would buy nothing.

``StackSim.vector()`` is MuJoCo's whole integration state (``mjSTATE_INTEGRATION``: positions, velocities,
controls, warm-start accelerations, time), so ``restore`` then ``step`` repeats a run bit for bit.
"""

from __future__ import annotations

import mujoco
import numpy as np

CUBE_SIDE = 0.04
HALF = CUBE_SIDE / 2
CONTROL_HZ = 10
TIMESTEP = 0.004
SUBSTEPS = round(1.0 / (CONTROL_HZ * TIMESTEP))  # physics steps per action
MAX_OPENING = 0.09  # the fingers' largest gap (m)
# Each action entry's range (x, y, z, opening); the layout's one box [-0.2, 0.2] holds them all.
ACTION_LOW = np.array([-0.2, -0.2, 0.015, 0.0])
ACTION_HIGH = np.array([0.2, 0.2, 0.2, MAX_OPENING])
TABLE_HALF = 1.2  # the table top spans [-1.2, 1.2]^2: it fills the camera's view (the renderer draws it as the ground)
FINGER = (0.005, 0.012, 0.025)  # finger box half sizes; its pad (inner face) at +-opening/2 from the grasp centre
FINGER_Z = 0.01  # finger box centre above the grasp centre: the fingertips reach 15 mm below it
PALM = (0.045, 0.015, 0.008)
PALM_Z = FINGER_Z + FINGER[2] + PALM[2]
RED, BLUE, GRIPPER_RGBA = (0.85, 0.2, 0.2), (0.2, 0.35, 0.85), (0.55, 0.55, 0.6)
TABLE_RGBA = (0.82, 0.72, 0.58)
CAMERA_POS, CAMERA_TARGET, CAMERA_FOVY = (0.0, -0.40, 0.34), (0.0, 0.0, 0.04), 45.0
STATE_DIM = 18  # gripper x, y, z, opening; red cube x, y, z, qw, qx, qy, qz; blue cube the same
CUBES = ("red", "blue")  # the red cube goes on top of the blue one


def _camera_axes() -> str:
    """MJCF ``xyaxes`` of the fixed camera looking from ``CAMERA_POS`` at ``CAMERA_TARGET``, level (no roll)."""
    forward = np.subtract(CAMERA_TARGET, CAMERA_POS)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return " ".join(f"{v:.9f}" for v in (*right, *up))


def _vec(values: tuple[float, ...] | np.ndarray) -> str:
    return " ".join(f"{v:g}" for v in values)


def _cube(name: str, rgba: tuple[float, ...], x: float) -> str:
    return (f'<body name="{name}" pos="{x} 0 {HALF}"><freejoint name="{name}"/>'
            f'<geom name="{name}" type="box" size="{HALF} {HALF} {HALF}" mass="0.05" rgba="{_vec(rgba)} 1"/></body>')


def _finger(name: str, sign: int) -> str:
    return (f'<body name="{name}" pos="0 0 0" gravcomp="1">'
            f'<joint name="{name}" type="slide" axis="{sign} 0 0" range="0 {MAX_OPENING / 2}" damping="1"/>'
            f'<geom name="{name}" type="box" size="{_vec(FINGER)}" pos="{sign * FINGER[0]} 0 {FINGER_Z}" mass="0.05" '
            f'priority="1" friction="0.25 0.005 0.0001" rgba="{_vec(GRIPPER_RGBA)} 1"/></body>')


MJCF = f"""
<mujoco model="gpc-stack">
  <option timestep="{TIMESTEP}" cone="elliptic" impratio="10" integrator="implicitfast"/>
  <visual><headlight ambient="0.35 0.35 0.35" diffuse="0.55 0.55 0.55" specular="0 0 0"/></visual>
  <default><geom friction="1 0.005 0.0001" condim="4" solref="0.01 1"/></default>
  <worldbody>
    <light directional="true" pos="0 0 1" dir="0 0 -1" diffuse="0.3 0.3 0.3" specular="0 0 0" castshadow="false"/>
    <geom name="table" type="box" size="{TABLE_HALF} {TABLE_HALF} 0.02" pos="0 0 -0.02" rgba="{_vec(TABLE_RGBA)} 1"/>
    <camera name="fixed" pos="{_vec(CAMERA_POS)}" xyaxes="{_camera_axes()}" fovy="{CAMERA_FOVY}"/>
    {_cube("red", RED, -0.06)}
    {_cube("blue", BLUE, 0.06)}
    <body name="hand" pos="0 0 0" gravcomp="1">
      <joint name="x" type="slide" axis="1 0 0" range="-0.3 0.3"/>
      <joint name="y" type="slide" axis="0 1 0" range="-0.3 0.3"/>
      <joint name="z" type="slide" axis="0 0 1" range="-0.05 0.4"/>
      <geom name="palm" type="box" size="{_vec(PALM)}" pos="0 0 {PALM_Z}" mass="0.5" rgba="{_vec(GRIPPER_RGBA)} 1"/>
      {_finger("left", -1)}
      {_finger("right", 1)}
    </body>
  </worldbody>
  <actuator>
    <position name="x" joint="x" kp="400" kv="40" forcerange="-15 15"/>
    <position name="y" joint="y" kp="400" kv="40" forcerange="-15 15"/>
    <position name="z" joint="z" kp="400" kv="40" forcerange="-15 15"/>
    <position name="left" joint="left" kp="300" kv="5" forcerange="-6 6"/>
    <position name="right" joint="right" kp="300" kv="5" forcerange="-6 6"/>
  </actuator>
</mujoco>
"""

_STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
# MuJoCo's warnings that it met a non-finite state and reset the data (counted since the last set_state or restore)
_DIVERGED = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)


class StackSim:
    """One MuJoCo model and data: set and read the 18-d state, step one action, save and restore exactly."""

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_string(MJCF)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._hand = [m.joint(n).qposadr[0] for n in ("x", "y", "z")]
        self._fingers = [m.joint(n).qposadr[0] for n in ("left", "right")]
        self._cubes = [m.joint(n).qposadr[0] for n in CUBES]
        self._cube_dofs = [m.joint(n).dofadr[0] for n in CUBES]
        self.geoms = {n: m.geom(n).id for n in ("table", "palm", "left", "right", *CUBES)}
        self.vector_size = mujoco.mj_stateSize(m, _STATE_SPEC)
        g = self.geoms  # geom pair -> the contact it counts as (0 gripper-red, 1 gripper-blue, 2 red-blue), else -1
        self._pair_kind = np.full((m.ngeom, m.ngeom), -1, dtype=int)
        for kind, (ones, others) in enumerate(((("palm", "left", "right"), ("red",)), (("palm", "left", "right"), ("blue",)),
                                               (("red",), ("blue",)))):
            for a in ones:
                for b in others:
                    self._pair_kind[g[a], g[b]] = self._pair_kind[g[b], g[a]] = kind
        self.set_state(np.array([0.0, 0.0, 0.12, MAX_OPENING, -0.06, 0, HALF, 1, 0, 0, 0, 0.06, 0, HALF, 1, 0, 0, 0]))

    # ------------------------------------------------------------------ state
    def set_state(self, state: np.ndarray) -> None:
        """Place everything at rest on an 18-d ``state`` (quaternions normalised), the actuators holding it there."""
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (STATE_DIM,) or not np.all(np.isfinite(state)):
            raise ValueError(f"a stack state is {STATE_DIM} finite numbers, got shape {state.shape}")
        mujoco.mj_resetData(self.model, self.data)
        qpos = self.data.qpos
        qpos[self._hand] = state[:3]
        qpos[self._fingers] = np.clip(state[3], 0.0, MAX_OPENING) / 2
        for i, adr in enumerate(self._cubes):
            pose = state[4 + 7 * i: 11 + 7 * i]
            qpos[adr:adr + 3] = pose[:3]
            qpos[adr + 3:adr + 7] = pose[3:] / np.linalg.norm(pose[3:])
        self.data.ctrl[:] = np.concatenate([state[:3], qpos[self._fingers]])
        mujoco.mj_forward(self.model, self.data)

    def state(self) -> np.ndarray:
        """``[gripper x, y, z, opening, red x, y, z, qw, qx, qy, qz, blue x, y, z, qw, qx, qy, qz]``.

        Quaternions are MuJoCo's, continuous along an episode, so ``q`` and ``-q`` (one orientation) both occur. Forcing
        ``qw >= 0`` made a tumbling cube's quaternion jump by up to 2 when ``qw`` crossed 0: 2% of the explorer's steps,
        73% of the squared quaternion change a world model is trained to predict, and its one-step prediction of the
        gripper, which a linear fit gets to 1 mm, 10 mm off.
        """
        qpos = self.data.qpos
        out = [qpos[self._hand], [qpos[self._fingers].sum()]]
        for adr in self._cubes:
            out += [qpos[adr:adr + 3], qpos[adr + 3:adr + 7]]
        return np.concatenate(out).astype(np.float64)

    def vector(self) -> np.ndarray:
        """MuJoCo's full integration state (float64): all ``restore`` needs to repeat what follows exactly."""
        out = np.empty(self.vector_size)
        mujoco.mj_getState(self.model, self.data, out, _STATE_SPEC)
        return out

    def restore(self, vector: np.ndarray) -> None:
        vector = np.asarray(vector, dtype=np.float64)
        if vector.shape != (self.vector_size,):
            raise ValueError(f"a stack simulator state is {self.vector_size} numbers (this MuJoCo model's), got shape {vector.shape}")
        mujoco.mj_resetData(self.model, self.data)
        mujoco.mj_setState(self.model, self.data, vector, _STATE_SPEC)
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ dynamics
    def step(self, action: np.ndarray) -> np.ndarray:
        """Track ``action`` (clipped to its ranges) for one control period; contacts ``(3,)``: the physics steps with
        gripper-red, gripper-blue and red-blue contact."""
        target = np.clip(np.asarray(action, dtype=np.float64), ACTION_LOW, ACTION_HIGH)
        self.data.ctrl[:] = [target[0], target[1], target[2], target[3] / 2, target[3] / 2]
        counts = np.zeros(3, dtype=int)
        for _ in range(SUBSTEPS):
            mujoco.mj_step(self.model, self.data)
            counts += self.contacts()
        return counts

    def contacts(self) -> np.ndarray:
        """Whether gripper-red, gripper-blue and red-blue touch now ``(3,)`` of 0/1."""
        out = np.zeros(3, dtype=int)
        n = self.data.ncon
        if n:
            kinds = self._pair_kind[self.data.contact.geom1[:n], self.data.contact.geom2[:n]]
            out[kinds[kinds >= 0]] = 1
        return out

    def unstable(self) -> str | None:
        """Why the simulation can no longer be trusted (NaN, a penetration over 1 cm, a cube off the table), or None."""
        if not (np.all(np.isfinite(self.data.qpos)) and np.all(np.isfinite(self.data.qvel))) or any(
                self.data.warning[w].number for w in _DIVERGED):
            return "the simulation diverged (NaN or infinite state; MuJoCo reset it)"
        if self.data.ncon and float(np.min(self.data.contact.dist[: self.data.ncon])) < -0.01:
            return "bodies interpenetrate by more than 1 cm"
        if min(self.data.qpos[adr + 2] for adr in self._cubes) < -HALF:
            return "a cube fell off the table"
        return None

    def cube_speeds(self) -> np.ndarray:
        """Each cube's linear speed (m/s) ``(2,)``."""
        return np.array([np.linalg.norm(self.data.qvel[adr:adr + 3]) for adr in self._cube_dofs])
