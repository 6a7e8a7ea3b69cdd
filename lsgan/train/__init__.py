"""Training: one loop (:mod:`lsgan.train.loop`) and what each model contributes to it (vae, gan, diffusion,
evaluator)."""
