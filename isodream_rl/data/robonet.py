"""RoboNet trajectories in their released HDF5 layout (``SudeepDasari/RoboNet``), read with h5py.

Layout of one ``.hdf5`` file::

    env/state                   [T, sdim] float
    env.attrs                   n_cams, cam_encoding ("mp4" or "jpg")
    env/cam{i}_video/frames     uint8 bytes of one mp4 file (attrs: shape, T, image_format)   # mp4
    env/cam{i}_video/frame{t}   uint8 bytes of one jpg per frame (attrs: shape, image_format) # jpg
    policy/actions              [T - 1, adim] float
    misc/*, metadata.attrs      free-form metadata

Frames are decoded with PIL (jpg) or PyAV (mp4) and resized to the requested size (Iso-Dream: 64x64).
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image
from torch.utils.data import Dataset

__all__ = ["read_robonet_hdf5", "write_robonet_hdf5", "RoboNetDataset"]


def _require_h5py():
    try:
        import h5py
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ImportError("reading RoboNet needs h5py: pip install 'isodream-rl[video]'") from err
    return h5py


def _resize(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    height, width = size
    if frame.shape[:2] == (height, width):
        return frame
    shrinking = height * width < frame.shape[0] * frame.shape[1]
    method = Image.Resampling.BOX if shrinking else Image.Resampling.BICUBIC
    return np.asarray(Image.fromarray(frame).resize((width, height), method))


def _decode_mp4(blob: bytes) -> list[np.ndarray]:
    import av

    with av.open(io.BytesIO(blob), format="mp4") as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]


def read_robonet_hdf5(
    path: str | os.PathLike, *, camera: int = 0, image_size: tuple[int, int] | int = 64
) -> dict[str, np.ndarray]:
    """Read one RoboNet trajectory.

    Args:
        path: the ``.hdf5`` file.
        camera: camera index ``i`` (``env/cam{i}_video``).
        image_size: output ``(height, width)``, or one int for square frames.

    Returns:
        ``{"frames": uint8 [T, H, W, 3] RGB, "actions": float32 [T - 1, adim], "states": float32 [T, sdim]}``.

    Raises:
        KeyError: if the file lacks the groups of RoboNet's layout or the camera.
        ValueError: on an unknown frame encoding or image format.
    """
    h5py = _require_h5py()
    size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    with h5py.File(path, "r") as f:
        for key in ("env", "env/state", "policy/actions"):
            if key not in f:
                raise KeyError(f"{path}: missing '{key}'; not a RoboNet HDF5 file (found {list(f.keys())})")
        env = f["env"]
        n_cams = int(env.attrs.get("n_cams", 0))
        if not 0 <= camera < n_cams:
            raise KeyError(f"{path}: camera {camera} requested but env.attrs['n_cams'] = {n_cams}")
        encoding = env.attrs.get("cam_encoding", "jpg")
        encoding = encoding.decode() if isinstance(encoding, bytes) else str(encoding)
        group = env[f"cam{camera}_video"]
        if encoding == "mp4":
            node = group["frames"]
            images = _decode_mp4(node[()].tobytes())[: int(node.attrs.get("T", 10**9))]
        elif encoding == "jpg":
            count = sum(1 for k in group if k.startswith("frame"))
            node = group["frame0"]
            images = [
                np.asarray(Image.open(io.BytesIO(group[f"frame{t}"][()].tobytes())).convert("RGB"))
                for t in range(count)
            ]
        else:
            raise ValueError(f"{path}: cam_encoding must be 'mp4' or 'jpg', got {encoding!r}")
        image_format = node.attrs.get("image_format", "RGB")
        image_format = image_format.decode() if isinstance(image_format, bytes) else str(image_format)
        if image_format not in ("RGB", "BGR"):
            raise ValueError(f"{path}: image_format must be 'RGB' or 'BGR', got {image_format!r}")
        # The encoders stored the array as given; a BGR array decodes with its channels swapped.
        frames = np.stack([_resize(img[..., ::-1] if image_format == "BGR" else img, size) for img in images])
        return {
            "frames": np.ascontiguousarray(frames),
            "actions": np.asarray(f["policy/actions"][()], dtype=np.float32),
            "states": np.asarray(env["state"][()], dtype=np.float32),
        }


def _encode_mp4(frames: np.ndarray, fps: int = 10) -> bytes:
    import av

    buf = io.BytesIO()
    with av.open(buf, mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuv444p"
        stream.options = {"crf": "0"}
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())
    return buf.getvalue()


def write_robonet_hdf5(
    path: str | os.PathLike,
    frames: np.ndarray,
    actions: np.ndarray,
    states: np.ndarray,
    *,
    encoding: str = "jpg",
) -> None:
    """Write one trajectory in RoboNet's HDF5 layout (one camera).

    Args:
        path: output file.
        frames: uint8 ``[T, H, W, 3]`` RGB.
        actions: ``[T - 1, adim]``.
        states: ``[T, sdim]``.
        encoding: ``"jpg"`` (one jpg per frame, quality 95) or ``"mp4"`` (lossless H.264, yuv444).
    """
    h5py = _require_h5py()
    if actions.shape[0] != frames.shape[0] - 1:
        raise ValueError(
            f"RoboNet stores T - 1 actions: got {actions.shape[0]} actions for {frames.shape[0]} frames"
        )
    with h5py.File(path, "w") as f:
        f.create_dataset("file_version", data="0.1.0")
        env = f.create_group("env")
        env.attrs["n_cams"] = 1
        env.attrs["cam_encoding"] = encoding
        env.create_dataset("state", data=np.asarray(states, dtype=np.float64))
        cam = env.create_group("cam0_video")
        if encoding == "mp4":
            node = cam.create_dataset("frames", data=np.frombuffer(_encode_mp4(frames), dtype=np.uint8))
            node.attrs["T"] = frames.shape[0]
            node.attrs["shape"] = frames.shape[1:]
            node.attrs["image_format"] = "RGB"
        elif encoding == "jpg":
            for t, frame in enumerate(frames):
                buf = io.BytesIO()
                Image.fromarray(frame).save(buf, format="JPEG", quality=95)
                node = cam.create_dataset(f"frame{t}", data=np.frombuffer(buf.getvalue(), dtype=np.uint8))
                node.attrs["shape"] = frame.shape
                node.attrs["image_format"] = "RGB"
        else:
            raise ValueError(f"encoding must be 'mp4' or 'jpg', got {encoding!r}")
        f.create_group("policy").create_dataset("actions", data=np.asarray(actions, dtype=np.float64))
        f.create_group("misc")
        f.create_group("metadata").attrs["robot"] = "synthetic"


class RoboNetDataset(Dataset):
    """RoboNet trajectories from a directory of ``.hdf5`` files, aligned to one action per frame.

    RoboNet stores ``T - 1`` actions; like Iso-Dream a zero action is appended so that ``actions[t]``
    moves frame ``t`` to ``t + 1`` and the arrays have equal length. Actions narrower than
    ``action_dim`` are zero-padded (Iso-Dream pads 4-d to 5-d); wider ones raise.

    Args:
        paths: a directory of ``.hdf5`` files or a list of files.
        camera: camera index.
        image_size: output side (or ``(height, width)``).
        action_dim: width to pad actions to; ``None`` keeps each file's own width.
    """

    def __init__(
        self,
        paths: str | os.PathLike | Iterable[str | os.PathLike],
        *,
        camera: int = 0,
        image_size: tuple[int, int] | int = 64,
        action_dim: int | None = 5,
    ) -> None:
        if isinstance(paths, str | os.PathLike):
            root = Path(paths)
            files = sorted(root.glob("*.hdf5")) if root.is_dir() else [root]
        else:
            files = [Path(p) for p in paths]
        if not files:
            raise FileNotFoundError(f"no .hdf5 files found at {paths}")
        self.files = files
        self.camera = camera
        self.image_size = image_size
        self.action_dim = action_dim

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        item = read_robonet_hdf5(self.files[index], camera=self.camera, image_size=self.image_size)
        actions = item["actions"]
        width = actions.shape[1] if self.action_dim is None else self.action_dim
        if actions.shape[1] > width:
            raise ValueError(
                f"{self.files[index]}: actions have {actions.shape[1]} dims, more than action_dim={width}"
            )
        aligned = np.zeros((item["frames"].shape[0], width), dtype=np.float32)
        aligned[: actions.shape[0], : actions.shape[1]] = actions
        item["actions"] = aligned
        return item
