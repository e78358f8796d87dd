"""The swap scene: Push-T's walls, rates and PD-controlled disc agent (``gpc.tasks.planar``), a cube and a sphere.

Both objects are dynamic pymunk bodies of mass 1 (the T's) with frictionless shapes (Push-T's friction), in a space
without velocity memory (damping 0): an object moves only during a tick in which something pushes it, so a push is
quasi-static and stops where the agent stops. The agent is kinematic (infinite mass), so the masses only decide how
a push through one object into the other shares its motion: equal masses push the pair alike whichever leads.
Frictionless contacts push along the contact normal, so a push's effect is predictable from the geometry: the
sphere moves along the line of centres, the cube along its face's normal, turning by the lever of the contact. The
sphere never turns (no contact can exert torque on it); its angle is kept in the snapshot for exactness only.
"""

from __future__ import annotations

import numpy as np
import pymunk

from gpc.tasks.planar.scene import AgentScene, contact_ticks
from gpc.tasks.swap.geometry import CUBE_SIDE, SPHERE_RADIUS

STATE_DIM = 7  # agent x, y; cube x, y, angle (mod 2 pi); sphere x, y
SIM_DIM = 16  # agent x, y, vx, vy; cube x, y, angle, vx, vy, omega; sphere x, y, angle, vx, vy, omega
AGENT, CUBE, SPHERE = 1, 2, 3  # collision types; the walls keep pymunk's 0
PAIRS = ((AGENT, CUBE), (AGENT, SPHERE), (CUBE, SPHERE))  # the contacts counted (object-wall contacts are not)


class SwapSim(AgentScene):
    """A kinematic disc under PD control, a square cube and a round sphere, all inside Push-T's walls."""

    def __init__(self) -> None:
        super().__init__()
        self.agent_shape.collision_type = AGENT
        s = CUBE_SIDE
        self.cube = pymunk.Body(1.0, pymunk.moment_for_box(1.0, (s, s)))
        self.cube.position = (160.0, 256.0)
        cube_shape = pymunk.Poly.create_box(self.cube, (s, s))
        cube_shape.collision_type = CUBE
        self.sphere = pymunk.Body(1.0, pymunk.moment_for_circle(1.0, 0.0, SPHERE_RADIUS))
        self.sphere.position = (352.0, 256.0)
        sphere_shape = pymunk.Circle(self.sphere, SPHERE_RADIUS)
        sphere_shape.collision_type = SPHERE
        self.space.add(self.cube, cube_shape, self.sphere, sphere_shape)
        self.contact_points = [0, 0, 0]
        for i, (a, b) in enumerate(PAIRS):
            self.space.on_collision(a, b, post_solve=self._counter(i))

    def _counter(self, i: int):
        def count(arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
            self.contact_points[i] += len(arbiter.contact_point_set.points)

        return count

    # ------------------------------------------------------------------ state
    def set_state(self, state: np.ndarray) -> None:
        """Place the agent and both objects at rest exactly on a 7-d ``state`` (the sphere unturned); no tick is stepped."""
        x = [float(v) for v in state]
        self.restore(np.array([x[0], x[1], 0.0, 0.0, x[2], x[3], x[4], 0.0, 0.0, 0.0, x[5], x[6], 0.0, 0.0, 0.0, 0.0]))

    def state(self) -> np.ndarray:
        """``[agent x, y, cube x, y, cube angle mod 2pi, sphere x, y]``."""
        a, c, s = self.agent.position, self.cube.position, self.sphere.position
        return np.array([a.x, a.y, c.x, c.y, self.cube.angle % (2 * np.pi), s.x, s.y])

    def cube_pose(self) -> np.ndarray:
        c = self.cube.position
        return np.array([c.x, c.y, self.cube.angle])

    def vector(self) -> np.ndarray:
        """``(16,)`` float64: every body's pose and velocities, all ``restore`` needs."""
        a, av = self.agent.position, self.agent.velocity
        out = [a.x, a.y, av.x, av.y]
        for body in (self.cube, self.sphere):
            p, v = body.position, body.velocity
            out += [p.x, p.y, body.angle, v.x, v.y, body.angular_velocity]
        return np.array(out, dtype=np.float64)

    def restore(self, vector: np.ndarray) -> None:
        """Return every body to ``vector`` exactly (pymunk's cached contacts are kept, as a live scene has them)."""
        v = [float(x) for x in vector]
        self.agent.position, self.agent.velocity = (v[0], v[1]), (v[2], v[3])
        for body, i in ((self.cube, 4), (self.sphere, 10)):
            body.angle = v[i + 2]
            body.position = (v[i], v[i + 1])
            body.velocity, body.angular_velocity = (v[i + 3], v[i + 4]), v[i + 5]
        for body in (self.cube, self.sphere):
            self.space.reindex_shapes_for_body(body)

    def restore_clean(self, vector: np.ndarray) -> None:
        """``restore`` after letting cached contacts lapse: what a private lookahead scene does, so that every
        lookahead from one vector is the same whatever the scene did before."""
        self.lapse_contacts((self.cube, self.sphere))
        self.restore(vector)

    # ------------------------------------------------------------------ dynamics
    def step(self, action: np.ndarray) -> np.ndarray:
        """Track target ``action`` (px) for one control period; contacts per tick ``(3,)``: agent-cube, agent-sphere,
        cube-sphere."""
        self.contact_points = [0, 0, 0]
        self.drive(action)
        return np.array([contact_ticks(n) for n in self.contact_points])
