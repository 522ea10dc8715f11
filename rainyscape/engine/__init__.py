"""Training engine: phases, optimisers, callbacks, checkpoints. Knows no NeRF, Gaussian or rain."""
