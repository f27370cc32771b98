"""The DreamerV2-style learner's modules (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``): encoder, RSSM
cells, decoders, mask composition, heads, world model, actor, value and acting policy."""
