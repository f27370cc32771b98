"""Hydra configuration groups of ``isodream-train`` (env, size, algo); see ``config.yaml``."""
