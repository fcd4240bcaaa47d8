"""Validated frame metadata: camera pose and pinhole intrinsics."""

from __future__ import annotations

import math
from dataclasses import dataclass

from service.errors import InvalidInput


@dataclass(frozen=True)
class Pose:
    """Camera-to-world pose: unit quaternion (w, x, y, z) and translation (metres)."""

    rotation: tuple[float, float, float, float]
    translation: tuple[float, float, float]

    @classmethod
    def from_lists(cls, rotation: list[float], translation: list[float]) -> Pose:
        if len(rotation) != 4 or len(translation) != 3:
            raise InvalidInput(
                "pose needs 'rotation' as a quaternion [w, x, y, z] and 'translation' [x, y, z]"
            )
        values = [*rotation, *translation]
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise InvalidInput("pose values must be finite numbers")
        norm = math.sqrt(sum(q * q for q in rotation))
        if abs(norm - 1.0) > 1e-2:
            raise InvalidInput(f"pose rotation must be a unit quaternion; its norm is {norm:.4f}")
        w, x, y, z = (q / norm for q in rotation)
        tx, ty, tz = (float(t) for t in translation)
        return cls((w, x, y, z), (tx, ty, tz))


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera intrinsics in pixels of the uploaded image."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise InvalidInput("intrinsics must be finite numbers")
        if self.fx <= 0 or self.fy <= 0:
            raise InvalidInput("intrinsics fx and fy must be positive")
