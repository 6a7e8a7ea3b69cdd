"""lsgan: text- and action-to-motion synthesis with a GAN in the latent space of a motion VAE."""

__version__ = "0.1.0"
