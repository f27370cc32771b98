"""The size presets of ``isodream-train`` (``model.size``): the one home of their widths.

The ``size`` group (``isodream_rl/configs/size/*.yaml``) names one of them and sets the rest of a run's scale
there (behavior widths, replay windows, schedule), never a world-model width. Each learner reads them its own
way: the DreamerV2-style world model takes them as they are (:class:`~isodream_rl.modules.isodream_v2.config.IsoDreamV2Config`),
the default derives DreamerV3's widths from ``hidden_dim`` (:mod:`isodream_rl.trainers.isodream`), the TorchRL
baselines read the ones they name."""

#: Size presets. ``paper``: Table 5 and the authors' configs (cnn depth 32, deter 200, stoch 50,
#: MLP units 400); ``small``: quick CPU runs; ``bench``: the learning bench's (``small`` at half its
#: convolution depth and GRU width, ``size=bench``); ``tiny``: unit tests.
SIZE_PRESETS: dict[str, dict[str, int]] = {
    "paper": {"depth": 32, "state_dim": 50, "belief_dim": 200, "hidden_dim": 200, "units": 400},
    "small": {"depth": 16, "state_dim": 32, "belief_dim": 128, "hidden_dim": 128, "units": 256},
    "bench": {"depth": 8, "state_dim": 32, "belief_dim": 64, "hidden_dim": 64, "units": 256},
    "tiny": {"depth": 4, "state_dim": 8, "belief_dim": 16, "hidden_dim": 16, "units": 32},
}
