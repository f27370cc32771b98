"""Recipes on a trained world model: the latent probe (:mod:`isodream_rl.recipes.latent_probe`: which sprites each
branch's state carries), which ``isodream-train exp=world_model`` runs at the end of a sprites run."""
