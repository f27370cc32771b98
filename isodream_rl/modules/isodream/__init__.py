"""The default learner's modules (``algo=isodream``): Iso-Dream's decoupled world model on TorchRL's DreamerV3
parts (:mod:`~isodream_rl.modules.isodream.world_model`) and its actor, critic and acting policy
(:mod:`~isodream_rl.modules.isodream.behavior`)."""
