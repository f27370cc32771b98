"""The DreamerV2-style learner's objectives (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``): the
world-model loss (eq. 5), KL balancing, imagination, the actor and value losses."""
