"""Models: the motion VAE, the latent GANs, text encoders, and their checkpoints."""
