"""The default learner's modules (``algo=isodream`` and its ablations): Iso-Dream's decoupled world model on TorchRL's
DreamerV3 parts (:mod:`~isodream_rl.modules.isodream.world_model`: eqs. 2-5) and its actor, critic and acting policy
(:mod:`~isodream_rl.modules.isodream.behavior`: eqs. 6-7, Algorithm 1 lines 19-22). :mod:`isodream_rl.modules`
exports them."""
