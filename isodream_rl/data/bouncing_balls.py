"""Bouncing-ball distractors overlaid on video frames (the paper's "BAIR/RoboNet with bouncing balls").

The balls are a noncontrollable, predictable dynamic: they move at constant speed, reflect off the image
borders and ignore the robot's actions. As in the authors' loader they are drawn at load time on top of
the frames; unlike it, the draw is seeded, and can be tied to the sample index so the test split is
fixed across runs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ball_trajectories", "overlay_balls", "BouncingBalls"]

# Pure red, green and blue discs, as in the authors' loader.
DEFAULT_COLORS: tuple[tuple[int, int, int], ...] = ((255, 0, 0), (0, 255, 0), (0, 0, 255))


def ball_trajectories(
    num_frames: int,
    *,
    rng: np.random.Generator,
    num_balls: int = 3,
    radius: int = 3,
    speed: int = 4,
    image_size: int = 64,
) -> np.ndarray:
    """Centre positions of balls bouncing off the image borders.

    Each ball starts uniformly in ``[radius, image_size - 1 - radius]^2`` and moves ``speed`` pixels per
    frame along each axis (random signs); a coordinate reaching a border is reflected back inside.

    Args:
        num_frames: T.
        rng: the random generator.
        num_balls: N.
        radius: disc radius in pixels.
        speed: pixels per frame along each axis.
        image_size: side of the square image.

    Returns:
        float array ``[T, N, 2]`` of (row, column) centres.
    """
    low, high = float(radius), float(image_size - 1 - radius)
    if high <= low:
        raise ValueError(f"image_size={image_size} is too small for balls of radius {radius}")
    pos = rng.uniform(low, high, size=(num_balls, 2))
    vel = speed * rng.choice([-1.0, 1.0], size=(num_balls, 2))
    out = np.empty((num_frames, num_balls, 2))
    for t in range(num_frames):
        out[t] = pos
        pos = pos + vel
        over, under = pos > high, pos < low
        pos = np.where(over, 2 * high - pos, np.where(under, 2 * low - pos, pos))
        vel = np.where(over | under, -vel, vel)
    return out


def overlay_balls(
    frames: np.ndarray,
    positions: np.ndarray,
    *,
    radius: int = 3,
    colors: tuple[tuple[int, int, int], ...] = DEFAULT_COLORS,
) -> np.ndarray:
    """Draw filled discs on a copy of ``frames``.

    Args:
        frames: uint8 ``[T, H, W, 3]``.
        positions: ``[T, N, 2]`` (row, column) centres, from :func:`ball_trajectories`.
        radius: disc radius in pixels.
        colors: one RGB colour per ball (cycled if there are fewer colours than balls).

    Returns:
        uint8 ``[T, H, W, 3]``.
    """
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be [T, H, W, 3], got shape {frames.shape}")
    if positions.shape[0] != frames.shape[0] or positions.shape[-1] != 2:
        raise ValueError(f"positions must be [T={frames.shape[0]}, N, 2], got shape {positions.shape}")
    out = frames.copy()
    rows = np.arange(frames.shape[1])[None, :, None]
    cols = np.arange(frames.shape[2])[None, None, :]
    for n in range(positions.shape[1]):
        cy = np.rint(positions[:, n, 0])[:, None, None]
        cx = np.rint(positions[:, n, 1])[:, None, None]
        disc = (rows - cy) ** 2 + (cols - cx) ** 2 <= radius**2
        out[disc] = colors[n % len(colors)]
    return out


class BouncingBalls:
    """Load-time transform adding bouncing balls to a ``[T, H, W, 3]`` uint8 clip.

    Args:
        num_balls: number of discs (paper: 3).
        radius: disc radius in pixels (paper: 3).
        speed: pixels per frame along each axis (paper: 4).
        seed: seed of the draws.
        fixed: if ``True`` the balls of sample ``i`` are a function of ``(seed, i)`` only, so every
            epoch and every run sees the same balls (use it for the test split). If ``False`` each call
            draws new balls from one generator seeded once.

    Examples:
        >>> import numpy as np
        >>> clip = np.zeros((12, 64, 64, 3), np.uint8)
        >>> BouncingBalls(fixed=True)(clip, index=0).shape
        (12, 64, 64, 3)
    """

    def __init__(
        self, *, num_balls: int = 3, radius: int = 3, speed: int = 4, seed: int = 0, fixed: bool = False
    ) -> None:
        self.num_balls = num_balls
        self.radius = radius
        self.speed = speed
        self.seed = seed
        self.fixed = fixed
        self._rng = np.random.default_rng(seed)

    def state_dict(self) -> dict:
        """The state of the generator the non-fixed draws come from (restore with :meth:`load_state_dict`)."""
        return {"rng": self._rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        self._rng.bit_generator.state = state["rng"]

    def __call__(self, frames: np.ndarray, index: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, index]) if self.fixed else self._rng
        positions = ball_trajectories(
            frames.shape[0],
            rng=rng,
            num_balls=self.num_balls,
            radius=self.radius,
            speed=self.speed,
            image_size=min(frames.shape[1], frames.shape[2]),
        )
        return overlay_balls(frames, positions, radius=self.radius)
