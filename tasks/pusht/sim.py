"""The Push-T physics: Diffusion Policy's pymunk scene, stepped without rendering.

Kept apart from the Gymnasium wrapper because planners (the ground-truth world model) need
a bare simulator they can save, restore and step thousands of times per decision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymunk

from gpc.tasks.planar.scene import DT, AgentScene, contact_ticks
from gpc.tasks.pusht.geometry import TEE_BOXES

StateVector = np.ndarray  # (5,): agent x, agent y, block x, block y, block angle


@dataclass(frozen=True)
class SimSnapshot:
    """Everything that determines the future of the scene: bodies' poses and velocities."""

    agent: tuple[float, float, float, float]  # x, y, vx, vy
    block: tuple[float, float, float, float, float, float]  # x, y, angle, vx, vy, omega


class PushTSim(AgentScene):
    """Diffusion Policy's Push-T scene: a kinematic disc under PD control pushing a T."""

    def __init__(self) -> None:
        super().__init__()
        self.block = self._add_tee()
        self.n_contact_points = 0
        self.space.on_collision(0, 0, post_solve=self._count_contacts)

    def _add_tee(self) -> pymunk.Body:
        shapes_vertices = [[tuple(v) for v in box] for box in TEE_BOXES.tolist()]
        # Diffusion Policy gives the T twice the bar's moment (it reuses the bar's vertices
        # for the stem); the human data was recorded with that quirk, so it is kept.
        moment = 2 * pymunk.moment_for_poly(1.0, shapes_vertices[0])
        body = pymunk.Body(1.0, moment)
        shapes = [pymunk.Poly(body, v) for v in shapes_vertices]
        body.center_of_gravity = tuple(
            (np.asarray(shapes[0].center_of_gravity) + np.asarray(shapes[1].center_of_gravity)) / 2
        )
        body.position = (256.0, 300.0)
        body.angle = 0.0
        self.space.add(body, *shapes)
        return body

    def _count_contacts(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        self.n_contact_points += len(arbiter.contact_point_set.points)

    # ------------------------------------------------------------------ state
    def set_state(self, state: StateVector, legacy: bool = False) -> None:
        """Place agent and block, then settle one physics tick as Diffusion Policy does.

        pymunk rotates a body about its centre of gravity, so the angle is set before the
        position to land exactly on ``state``; ``legacy`` keeps the original test-set order
        (position first), which leaves the block rotated away from the drawn position.
        """
        x = [float(v) for v in state]
        self.agent.position = (x[0], x[1])
        self.agent.velocity = (0.0, 0.0)
        self.block.velocity = (0.0, 0.0)
        self.block.angular_velocity = 0.0
        if legacy:
            self.block.position = (x[2], x[3])
            self.block.angle = x[4]
        else:
            self.block.angle = x[4]
            self.block.position = (x[2], x[3])
        self.space.step(DT)
        self.space.reindex_shapes_for_body(self.block)

    def state(self) -> StateVector:
        """``[agent_x, agent_y, block_x, block_y, block_angle mod 2pi]``."""
        a, b = self.agent.position, self.block.position
        return np.array([a.x, a.y, b.x, b.y, self.block.angle % (2 * np.pi)])

    def block_pose(self) -> np.ndarray:
        b = self.block.position
        return np.array([b.x, b.y, self.block.angle])

    def snapshot(self) -> SimSnapshot:
        a, av = self.agent.position, self.agent.velocity
        b, bv = self.block.position, self.block.velocity
        return SimSnapshot(
            (a.x, a.y, av.x, av.y), (b.x, b.y, self.block.angle, bv.x, bv.y, self.block.angular_velocity)
        )

    def restore(self, snap: SimSnapshot) -> None:
        """Return to ``snap`` exactly (no settling tick, unlike ``set_state``)."""
        ax, ay, avx, avy = snap.agent
        bx, by, ba, bvx, bvy, bw = snap.block
        self.agent.position = (ax, ay)
        self.agent.velocity = (avx, avy)
        self.block.angle = ba
        self.block.position = (bx, by)
        self.block.velocity = (bvx, bvy)
        self.block.angular_velocity = bw

    def restore_clean(self, snap: SimSnapshot) -> None:
        """``restore`` after letting cached contacts lapse, for a private lookahead scene.

        pymunk keeps contacts (and their warm-start impulses) a few ticks and cannot save
        them; parking the agent far away for 4 empty ticks clears them, so every lookahead
        from the same snapshot is the same, whatever the scene did before.
        """
        self.lapse_contacts()
        self.restore(snap)

    # ------------------------------------------------------------------ dynamics
    def step(self, action: np.ndarray) -> int:
        """Track target ``action`` (px) for one control period; returns contact points per tick (walls included)."""
        self.n_contact_points = 0
        self.drive(action)
        return contact_ticks(self.n_contact_points)
