"""The rain module: rain head, Langevin latent updates, rain-angle estimation."""
