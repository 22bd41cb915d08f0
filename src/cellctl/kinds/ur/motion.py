"""The arm's geometry and motion time, per model: pure functions, no I/O, no clock.

The e-Series arms by UR's published Denavit-Hartenberg parameters and reach; a move's time
by a trapezoidal profile (accelerate at ``a``, cruise at ``v``, decelerate), as the
controller plans ``movej`` (in joint space: the joint that travels farthest) and ``movel``
(along the tool's straight line)::

    arm = ARMS["UR5e"]
    arm.tcp(HOME)                       # (x, y, z, rx, ry, rz), m and rad
    move_time(distance=1.2, v=1.05, a=1.4)
    arm.solve((0.4, 0.2, 0.3), start=HOME)   # joints that put the tool there (position only)

The inverse kinematics here is numerical and positional (the tool's orientation is not
matched): enough to time a move to a pose and show the arm where it went, not to plan one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

Joints = tuple[float, float, float, float, float, float]
Pose = tuple[float, float, float, float, float, float]

#: Joints at the controller's start: the arm upright.
HOME: Joints = (0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0)
#: Joint limits, rad (every e-Series joint turns ±360°).
JOINT_LIMIT = 2 * math.pi
#: movej's defaults (rad/s², rad/s) and movel's (m/s², m/s), as the URScript manual gives them.
MOVEJ_A, MOVEJ_V = 1.4, 1.05
MOVEL_A, MOVEL_V = 1.2, 0.25
#: One control cycle of an e-Series controller (500 Hz), s: ``sync()`` waits one.
CYCLE_S = 0.002
_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
_COS_ALPHA = tuple(math.cos(x) for x in _ALPHA)
_SIN_ALPHA = tuple(math.sin(x) for x in _ALPHA)


@dataclass(frozen=True)
class Arm:
    """One model: its reach (m) and DH parameters ``d1, a2, a3, d4, d5, d6`` (m)."""

    name: str
    reach: float
    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float

    def _frames(self, q: Sequence[float]) -> list[list[float]]:
        a = (0.0, self.a2, self.a3, 0.0, 0.0, 0.0)
        d = (self.d1, 0.0, 0.0, self.d4, self.d5, self.d6)
        # The 3x4 transform, row by row, times each joint's DH matrix (its last row 0 0 0 1).
        r0: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0)
        r1: tuple[float, ...] = (0.0, 1.0, 0.0, 0.0)
        r2: tuple[float, ...] = (0.0, 0.0, 1.0, 0.0)
        for i in range(6):
            ct, st = math.cos(q[i]), math.sin(q[i])
            ca, sa = _COS_ALPHA[i], _SIN_ALPHA[i]
            m0 = (ct, -st * ca, st * sa, a[i] * ct)
            m1 = (st, ct * ca, -ct * sa, a[i] * st)
            m2 = (0.0, sa, ca, d[i])
            r0, r1, r2 = (
                tuple(
                    row[0] * m0[c] + row[1] * m1[c] + row[2] * m2[c] + (row[3] if c == 3 else 0.0)
                    for c in range(4)
                )
                for row in (r0, r1, r2)
            )
        return [[*r0, *r1, *r2]]

    def tcp(self, q: Sequence[float]) -> Pose:
        """The tool flange's pose for joints ``q``: position (m) and rotation vector (rad)."""
        t = self._frames(q)[0]
        return (t[3], t[7], t[11], *_rotation_vector(t))

    def position(self, q: Sequence[float]) -> tuple[float, float, float]:
        t = self._frames(q)[0]
        return t[3], t[7], t[11]

    def solve(
        self, target: Sequence[float], start: Sequence[float], iterations: int = 60
    ) -> Joints | None:
        """Joints near ``start`` that put the tool at ``target[:3]`` (None: not reached)."""
        q = list(start)
        goal = target[:3]
        for _ in range(iterations):
            here = self.position(q)
            err = [goal[i] - here[i] for i in range(3)]
            if math.sqrt(sum(e * e for e in err)) < 1e-4:
                return (q[0], q[1], q[2], q[3], q[4], q[5])
            # Damped least squares on the three joints that place the wrist.
            jac = []
            for j in range(3):
                dq = list(q)
                dq[j] += 1e-6
                p = self.position(dq)
                jac.append([(p[i] - here[i]) / 1e-6 for i in range(3)])
            # (J Jᵀ + λ²I) y = err ; Δq = Jᵀ y
            jjt = [
                [sum(jac[k][r] * jac[k][c] for k in range(3)) + (0.01 if r == c else 0.0)
                 for c in range(3)]
                for r in range(3)
            ]  # fmt: skip
            y = _solve3(jjt, err)
            if y is None:
                return None
            for j in range(3):
                q[j] += sum(jac[j][i] * y[i] for i in range(3))
        return None


def _solve3(m: list[list[float]], b: list[float]) -> list[float] | None:
    det = (
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    )
    if abs(det) < 1e-12:
        return None
    out = []
    for col in range(3):
        mm = [row[:] for row in m]
        for r in range(3):
            mm[r][col] = b[r]
        out.append(
            (
                mm[0][0] * (mm[1][1] * mm[2][2] - mm[1][2] * mm[2][1])
                - mm[0][1] * (mm[1][0] * mm[2][2] - mm[1][2] * mm[2][0])
                + mm[0][2] * (mm[1][0] * mm[2][1] - mm[1][1] * mm[2][0])
            )
            / det
        )
    return out


def _rotation_vector(t: Sequence[float]) -> tuple[float, float, float]:
    r = ((t[0], t[1], t[2]), (t[4], t[5], t[6]), (t[8], t[9], t[10]))
    cos = max(-1.0, min(1.0, (r[0][0] + r[1][1] + r[2][2] - 1) / 2))
    angle = math.acos(cos)
    if angle < 1e-9:
        return 0.0, 0.0, 0.0
    s = 2 * math.sin(angle)
    if abs(s) < 1e-9:  # 180°: the axis from the diagonal
        x = math.sqrt(max(0.0, (r[0][0] + 1) / 2))
        y = math.sqrt(max(0.0, (r[1][1] + 1) / 2))
        z = math.sqrt(max(0.0, (r[2][2] + 1) / 2))
        return x * angle, y * angle, z * angle
    return (
        (r[2][1] - r[1][2]) / s * angle,
        (r[0][2] - r[2][0]) / s * angle,
        (r[1][0] - r[0][1]) / s * angle,
    )


#: The models a cell may name (``options.model``), by UR's data sheets.
ARMS: dict[str, Arm] = {
    arm.name: arm
    for arm in (
        Arm("UR3e", 0.500, 0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
        Arm("UR5e", 0.850, 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
        Arm("UR10e", 1.300, 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
        Arm("UR16e", 0.900, 0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
    )
}


def move_time(distance: float, v: float, a: float, t: float = 0.0) -> float:
    """Seconds a move of ``distance`` takes at speed ``v`` and acceleration ``a`` (a
    trapezoid, or a triangle when it never reaches ``v``); ``t`` > 0 sets the time itself."""
    if t > 0:
        return t
    distance = abs(distance)
    if distance == 0:
        return 0.0
    if v <= 0 or a <= 0:
        return math.inf
    if distance >= v * v / a:
        return distance / v + v / a
    return 2 * math.sqrt(distance / a)


def joint_distance(q0: Sequence[float], q1: Sequence[float]) -> float:
    """The farthest any joint travels between ``q0`` and ``q1``, rad."""
    return max(abs(b - a) for a, b in zip(q0, q1, strict=True))


def line_distance(p0: Sequence[float], p1: Sequence[float]) -> float:
    """The tool's straight-line distance between two poses, m."""
    return math.dist(p0[:3], p1[:3])


def interpolate(q0: Sequence[float], q1: Sequence[float], fraction: float) -> Joints:
    """Joints ``fraction`` (0..1) of the way from ``q0`` to ``q1``."""
    f = max(0.0, min(1.0, fraction))
    v = [a + (b - a) * f for a, b in zip(q0, q1, strict=True)]
    return (v[0], v[1], v[2], v[3], v[4], v[5])
