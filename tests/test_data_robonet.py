"""RoboNet HDF5 reading, on files written here in RoboNet's layout with h5py (jpg and mp4 frames)."""

import io

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")
from PIL import Image  # noqa: E402

from isodream_rl.data import RoboNetDataset, read_robonet_hdf5, write_robonet_hdf5  # noqa: E402


def _smooth_frames(steps: int, height: int = 48, width: int = 64) -> np.ndarray:
    """Smooth gradients, so lossy codecs reproduce them closely."""
    y, x = np.mgrid[0:height, 0:width]
    frames = [
        np.stack([(x * 4 + 10 * t) % 256, (y * 5) % 256, np.full_like(x, 40 * t % 256)], -1)
        for t in range(steps)
    ]
    return np.stack(frames).astype(np.uint8)


def _write_jpg_file(path, frames, actions, states, image_format="RGB"):
    """RoboNet layout by hand: env/cam0_video/frame{t} jpg bytes, env/state, policy/actions, misc, metadata."""
    with h5py.File(path, "w") as f:
        f["file_version"] = "0.1.0"
        env = f.create_group("env")
        env.attrs["n_cams"] = 1
        env.attrs["cam_encoding"] = "jpg"
        env["state"] = states
        cam = env.create_group("cam0_video")
        for t, frame in enumerate(frames):
            stored = frame[..., ::-1] if image_format == "BGR" else frame
            buf = io.BytesIO()
            Image.fromarray(np.ascontiguousarray(stored)).save(buf, format="JPEG", quality=98)
            ds = cam.create_dataset(f"frame{t}", data=np.frombuffer(buf.getvalue(), dtype=np.uint8))
            ds.attrs["shape"] = frame.shape
            ds.attrs["image_format"] = image_format
        f.create_group("policy")["actions"] = actions
        f.create_group("misc")["camera_configuration"] = "fixed"
        f.create_group("metadata").attrs["robot"] = "sawyer"


@pytest.fixture
def trajectory():
    rng = np.random.default_rng(0)
    frames = _smooth_frames(5)
    return frames, rng.normal(size=(4, 4)), rng.normal(size=(5, 5))


@pytest.mark.parametrize("image_format", ["RGB", "BGR"])
def test_reads_handwritten_jpg_file(tmp_path, trajectory, image_format):
    frames, actions, states = trajectory
    _write_jpg_file(tmp_path / "t.hdf5", frames, actions, states, image_format)
    item = read_robonet_hdf5(tmp_path / "t.hdf5", image_size=(48, 64))
    assert item["frames"].shape == (5, 48, 64, 3) and item["frames"].dtype == np.uint8
    assert np.abs(item["frames"].astype(int) - frames).mean() < 3.0
    np.testing.assert_allclose(item["actions"], actions, rtol=1e-6)
    np.testing.assert_allclose(item["states"], states, rtol=1e-6)


def test_reads_mp4_blob_and_resizes(tmp_path, trajectory):
    frames, actions, states = trajectory
    write_robonet_hdf5(tmp_path / "m.hdf5", frames, actions, states, encoding="mp4")
    with h5py.File(tmp_path / "m.hdf5") as f:
        assert f["env"].attrs["cam_encoding"] == "mp4"
        assert f["env/cam0_video/frames"].attrs["T"] == 5
    full = read_robonet_hdf5(tmp_path / "m.hdf5", image_size=(48, 64))
    assert full["frames"].shape == (5, 48, 64, 3)
    assert np.abs(full["frames"].astype(int) - frames).mean() < 3.0
    assert read_robonet_hdf5(tmp_path / "m.hdf5")["frames"].shape == (5, 64, 64, 3)


def test_dataset_appends_zero_action_and_pads_width(tmp_path, trajectory):
    frames, actions, states = trajectory
    _write_jpg_file(tmp_path / "a.hdf5", frames, actions, states)
    item = RoboNetDataset(tmp_path, action_dim=5)[0]
    assert item["actions"].shape == (5, 5)
    np.testing.assert_allclose(item["actions"][:4, :4], actions, rtol=1e-6)
    assert not item["actions"][4].any() and not item["actions"][:, 4].any()


def test_missing_groups_raise_key_error(tmp_path):
    with h5py.File(tmp_path / "x.hdf5", "w") as f:
        f["something"] = 1
    with pytest.raises(KeyError, match="not a RoboNet"):
        read_robonet_hdf5(tmp_path / "x.hdf5")
