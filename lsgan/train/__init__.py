"""Training loops (VAE, GAN) and what they share: devices, distributed runs, logs."""
