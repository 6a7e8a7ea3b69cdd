"""Training loops (VAE, GAN, diffusion) and what they share: devices, distributed runs, logs."""
