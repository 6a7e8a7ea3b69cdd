"""Models: the motion VAE, the latent GANs, the latent-diffusion baseline, text encoders, and their checkpoints."""
