"""Drawn shapes that cross or wind, as a person draws them on the page: an "e", a loop, an
"alpha" and a "phi", each as several demonstrations with their own speed, a small affine
jitter and hand tremor, written as ``snds train --data`` CSV files (seeded).

    python benchmarks/drawn_shapes.py OUT_DIR     # OUT_DIR/e.csv, loop.csv, alpha.csv, phi.csv
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["SHAPES", "draw", "write_csv"]


def _e(s: np.ndarray) -> np.ndarray:
    # The bar from left to right, then counter-clockwise around, crossing the bar's start.
    bar = s < 0.3
    angle = np.where(bar, 0.0, (s - 0.3) / 0.7) * 1.75 * np.pi
    x = np.where(bar, -1.0 + 2.0 * s / 0.3, np.cos(angle))
    y = np.where(bar, 0.0, np.sin(angle))
    return np.stack([x, y], -1)


def _loop(s: np.ndarray) -> np.ndarray:
    # A trochoid: left to right with one loop in the middle.
    turn = 2.0 * np.pi * s
    return np.stack([3.0 * s + 1.2 * np.sin(turn), 1.2 * (1.0 - np.cos(turn))], -1)


def _alpha(s: np.ndarray) -> np.ndarray:
    angle = np.pi * (0.15 + 1.7 * s)
    return np.stack([0.6 * np.sin(2.0 * angle) + 0.5 * (s - 0.5), np.sin(angle)], -1)


def _phi(s: np.ndarray) -> np.ndarray:
    # A circle from the top, then a stroke down through it, crossing it twice.
    circle = s < 0.6
    angle = np.pi / 2 + 2.0 * np.pi * s / 0.6
    x = np.where(circle, np.cos(angle), 0.0)
    y = np.where(circle, np.sin(angle), 1.0 - 2.6 * (s - 0.6) / 0.4)
    return np.stack([x, y], -1)


#: The shapes by name, each a curve over s in [0, 1].
SHAPES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "e": _e,
    "loop": _loop,
    "alpha": _alpha,
    "phi": _phi,
}


def draw(
    name: str,
    *,
    demos: int = 7,
    samples: int = 400,
    seed: int = 0,
    scale: float = 100.0,
    rate: float = 100.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Demonstrations of one shape: (positions (T, 2), times (T,)) each, sampled at ``rate``
    Hz, with a slow start and end, a random pace, affine jitter and tremor."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(demos):
        count = samples + int(rng.integers(-samples // 5, samples // 5))
        t = np.linspace(0.0, 1.0, count)
        s = (1.0 - np.cos(np.pi * t ** rng.uniform(0.7, 1.3))) / 2.0
        warp = np.eye(2) + rng.normal(0.0, 0.06, (2, 2))
        points = SHAPES[name](s) @ warp.T + rng.normal(0.0, 0.05, 2)
        points = points + 0.3 * rng.normal(0.0, 0.004, points.shape).cumsum(0)
        out.append((scale * points, np.arange(count) / rate))
    return out


def write_csv(name: str, path: Path, **options: float) -> Path:
    """Writes the demonstrations of ``name`` as ``demo,t,x1,x2`` rows; returns ``path``."""
    rows = ["demo,t,x1,x2"]
    for d, (points, times) in enumerate(draw(name, **options)):
        rows += [f"{d},{t:.4f},{x:.4f},{y:.4f}" for t, (x, y) in zip(times, points)]
    path.write_text("\n".join(rows) + "\n")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name in SHAPES:
        print(write_csv(name, args.out / f"{name}.csv", seed=args.seed))


if __name__ == "__main__":
    main()
