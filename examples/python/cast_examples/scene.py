"""The synthetic scene the segmenter "sees", and what the recognisers know about looks.

A fixed table-top of objects with a true colour and shape; the segmenter
reports noisy features (mean RGB, corners, fill), the recognisers map
features back to names. Kept free of CAST so it can be read (and ported to
C++ or Java) on its own.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

__all__ = ["COLOURS", "SHAPES", "TrueObject", "features", "make_scene", "name_colour", "name_shape"]

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.12, 0.10),
    "green": (0.15, 0.70, 0.20),
    "blue": (0.12, 0.25, 0.85),
    "yellow": (0.90, 0.85, 0.15),
}
# shape -> (corners on the outline, share of the bounding box filled)
SHAPES: dict[str, tuple[int, float]] = {"cube": (4, 0.95), "ball": (0, math.pi / 4), "cone": (3, 0.5)}

# The table, left to right: the questions of configs/demo.yaml are about these.
_LAYOUT = [
    ("green", "cone", -0.45, 0.30),
    ("blue", "ball", -0.25, 0.55),
    ("red", "cube", 0.00, 0.40),
    ("yellow", "cube", 0.20, 0.35),
    ("red", "ball", 0.40, 0.60),
    ("blue", "cube", 0.55, 0.25),
    ("green", "ball", -0.60, 0.65),
    ("yellow", "cone", 0.70, 0.50),
]


@dataclass
class TrueObject:
    """An object as it really is."""

    label: str
    colour: str
    shape: str
    x: float
    y: float
    size: float


def make_scene(count: int, seed: int) -> list[TrueObject]:
    """The first ``count`` objects of the layout (at most 8), sizes drawn from ``seed``."""
    rng = random.Random(seed)
    return [TrueObject(f"obj-{i + 1}", colour, shape, x, y, round(rng.uniform(0.05, 0.09), 3))
            for i, (colour, shape, x, y) in enumerate(_LAYOUT[: max(1, min(count, len(_LAYOUT)))])]


def features(obj: TrueObject, rng: random.Random) -> dict[str, float | int]:
    """What the camera reports of an object: noisy colour, corners, fill."""
    r, g, b = COLOURS[obj.colour]
    corners, fill = SHAPES[obj.shape]
    jitter = lambda v: min(1.0, max(0.0, v + rng.gauss(0, 0.05)))  # noqa: E731
    return {"red": jitter(r), "green": jitter(g), "blue": jitter(b), "corners": corners, "fill": jitter(fill)}


def name_colour(red: float, green: float, blue: float) -> str:
    """The named colour nearest to a mean RGB."""
    return min(COLOURS, key=lambda n: sum((a - c) ** 2 for a, c in zip((red, green, blue), COLOURS[n], strict=True)))


def name_shape(corners: int, fill: float) -> str:
    """The shape whose outline and fill match best."""
    return min(SHAPES, key=lambda n: abs(SHAPES[n][0] - corners) + 4 * abs(SHAPES[n][1] - fill))
