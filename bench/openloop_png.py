"""A run's open-loop prediction GIF (``<run_dir>/pictures/openloop_<env steps>.gif``) as one still picture: a few
of its frames stacked downwards (time downwards: the labelled rows of truth, composite, each branch and its mask,
as the GIF draws them), for pages that cannot show a GIF.

    python bench/openloop_png.py <run_dir>/pictures/openloop_00025000.gif docs/results/isolation/picture.png

By default the frames at steps 0, 4, 8, 12 and the last one (the GIF's first ``logging.video_context`` steps are
observed, the rest imagined; its own labels say which).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from PIL import Image


def gif_frames(path: Path) -> list[Image.Image]:
    """Every frame of the GIF at ``path``, as RGB images."""
    gif = Image.open(path)
    frames = []
    for index in range(gif.n_frames):
        gif.seek(index)
        frames.append(gif.convert("RGB").copy())
    return frames


def stack_frames(frames: list[Image.Image], steps: list[int]) -> Image.Image:
    """The frames at ``steps`` (negative: from the end) stacked downwards.

    Raises:
        ValueError: a step outside the GIF.
    """
    bad = [s for s in steps if not -len(frames) <= s < len(frames)]
    if bad:
        raise ValueError(f"steps {bad} are outside the GIF's {len(frames)} frames")
    width, height = frames[0].size
    out = Image.new("RGB", (width, height * len(steps)), "white")
    for row, step in enumerate(steps):
        out.paste(frames[step], (0, row * height))
    return out


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("gif", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--steps", default="0,4,8,12,-1", help="the GIF's frames to keep, comma-separated")
    args = parser.parse_args(argv)
    picture = stack_frames(gif_frames(args.gif), [int(s) for s in args.steps.split(",")])
    args.png.parent.mkdir(parents=True, exist_ok=True)
    picture.save(args.png)
    return args.png


if __name__ == "__main__":
    main()
