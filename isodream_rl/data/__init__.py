"""Data: video-prediction sets (BAIR TFRecords, RoboNet HDF5, a local BAIR-like pusher set, bouncing balls), and
random-action episodes of the sprites scene with their ground truth (:mod:`isodream_rl.data.sprites_episodes`, not
imported here: it loads TorchRL)."""

from isodream_rl.data.bair import (
    BAIRDataset,
    decode_bair_example,
    encode_bair_example,
    write_bair_tfrecord,
    write_tiny_bair,
)
from isodream_rl.data.bouncing_balls import BouncingBalls, ball_trajectories, overlay_balls
from isodream_rl.data.clips import ArraySequences, VideoClips
from isodream_rl.data.pusher import default_cache_dir, generate_pusher_sequences, load_pusher_dataset
from isodream_rl.data.robonet import RoboNetDataset, read_robonet_hdf5, write_robonet_hdf5

__all__ = [
    "ArraySequences",
    "BAIRDataset",
    "BouncingBalls",
    "RoboNetDataset",
    "VideoClips",
    "ball_trajectories",
    "decode_bair_example",
    "default_cache_dir",
    "encode_bair_example",
    "generate_pusher_sequences",
    "load_pusher_dataset",
    "overlay_balls",
    "read_robonet_hdf5",
    "write_bair_tfrecord",
    "write_robonet_hdf5",
    "write_tiny_bair",
]
