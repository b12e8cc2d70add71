"""Road geometry of the video scenes: a centre line that may curve, on a sloped ground plane.

Scene frame (metres): gravity-aligned, x along the street's initial direction, y left, z up.
The centre line is straight up to arc length ``turn_start_m``, then a circular arc of
curvature ``curvature_per_m`` (positive = to the left) for ``turn_length_m``, then straight
again. Street coordinates ``(s, l)`` are the arc length along the centre line and the
signed lateral offset (left positive); the mapping is exact in both directions.

The ground is one plane of constant grade along the initial direction: ``z = grade * x``.
Road-bound things (cars, the ego car, sidewalks) lie on it; buildings, poles, trees and
people stand vertically (gravity), so they lean by the grade relative to the road.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Road", "rotation_z"]


def rotation_z(angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about +z (counter-clockwise seen from above)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Road:
    """Centre line and ground plane of one video scene.

    Attributes
    ----------
    turn_start_m : float, metres
        Arc length where the curve starts.
    turn_length_m : float, metres
        Length of the curve (0 = straight street).
    curvature_per_m : float, 1/m
        Curvature of the arc, positive turning left; ``|curvature| * 40 m < 1`` is assumed
        (everything placed within 40 m of the centre line maps back uniquely).
    grade : float
        Ground slope ``dz/dx`` (tan of the slope angle), positive uphill ahead.
    """

    turn_start_m: float = 0.0
    turn_length_m: float = 0.0
    curvature_per_m: float = 0.0
    grade: float = 0.0

    @property
    def curved(self) -> bool:
        return self.turn_length_m > 0.0 and self.curvature_per_m != 0.0

    @property
    def turn_angle(self) -> float:
        """Total heading change over the curve, radians."""
        return self.curvature_per_m * self.turn_length_m if self.curved else 0.0

    @property
    def ground_normal(self) -> np.ndarray:
        """(3,) unit normal of the ground plane (pointing up)."""
        g = self.grade
        k = 1.0 / math.sqrt(1.0 + g * g)
        return np.array([-g * k, 0.0, k])

    # -- centre line --------------------------------------------------------------------------
    def heading(self, s: float) -> float:
        """Direction of the centre line at arc length ``s`` (radians from +x)."""
        if not self.curved:
            return 0.0
        return self.curvature_per_m * min(max(s - self.turn_start_m, 0.0), self.turn_length_m)

    def centre(self, s: float) -> tuple[float, float]:
        """(x, y) of the centre line at arc length ``s``, metres."""
        if not self.curved or s <= self.turn_start_m:
            return float(s), 0.0
        k = self.curvature_per_m
        a = k * min(s - self.turn_start_m, self.turn_length_m)
        x = self.turn_start_m + math.sin(a) / k
        y = (1.0 - math.cos(a)) / k
        rest = s - self.turn_start_m - self.turn_length_m
        if rest > 0.0:
            x += rest * math.cos(a)
            y += rest * math.sin(a)
        return x, y

    def point(self, s: float, l: float) -> tuple[float, float, float]:
        """(x, y, heading) of street coordinates (``s`` along, ``l`` left of the centre line)."""
        x, y = self.centre(s)
        psi = self.heading(s)
        return x - l * math.sin(psi), y + l * math.cos(psi), psi

    def to_street(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Street coordinates (s, l) of world points, (N,) arrays in metres.

        Each piece (straight, arc, straight) gives a candidate where the point projects
        onto it; the one with the smallest ``|l|`` wins.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if not self.curved:
            return x.copy(), y.copy()
        s0, length, k = self.turn_start_m, self.turn_length_m, self.curvature_per_m
        s_out = np.where(x <= s0, x, np.nan)
        l_out = np.where(x <= s0, y, np.inf)
        # Arc: with C the centre of curvature, k (p - C) = (1 - k l) (sin a, -cos a).
        wx = k * (x - s0)
        wy = k * y - 1.0
        a = np.arctan2(wx, -wy)
        l_arc = (1.0 - np.sqrt(wx * wx + wy * wy)) / k
        on_arc = (a / k >= 0.0) & (a / k <= length)
        better = on_arc & (np.abs(l_arc) < np.abs(l_out))
        s_out = np.where(better, s0 + a / k, s_out)
        l_out = np.where(better, l_arc, l_out)
        # Final straight.
        x1, y1 = self.centre(s0 + length)
        a1 = self.turn_angle
        c, s = math.cos(a1), math.sin(a1)
        along = (x - x1) * c + (y - y1) * s
        across = -(x - x1) * s + (y - y1) * c
        better = (along >= 0.0) & (np.abs(across) < np.abs(l_out))
        s_out = np.where(better, s0 + length + along, s_out)
        l_out = np.where(better, across, l_out)
        # Behind the first straight's start nothing else applies (x <= s0 covers it).
        s_out = np.where(np.isnan(s_out), x, s_out)
        l_out = np.where(np.isinf(l_out), y, l_out)
        return s_out, l_out

    # -- ground ---------------------------------------------------------------------------------
    def ground_z(self, x: float, *, above: float = 0.0) -> float:
        """z at horizontal position ``x`` of the plane parallel to the ground, ``above``
        metres over it (measured along the normal)."""
        g = self.grade
        return g * x + above * math.sqrt(1.0 + g * g)

    def surface_rotation(self, heading: float) -> np.ndarray:
        """(3, 3) world-from-local rotation of a thing lying on the ground, facing ``heading``.

        Local x is the ground direction straight above which is the horizontal ``heading``,
        z the ground normal, y = z x x (left).
        """
        n = self.ground_normal
        c, s = math.cos(heading), math.sin(heading)
        f = np.array([c, s, self.grade * c])  # on the plane z = grade * x
        f = f / math.sqrt(float(f @ f))
        left = np.cross(n, f)
        return np.column_stack([f, left, n])
