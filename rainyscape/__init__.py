"""RainyScape: unsupervised rainy-scene reconstruction on NeRF and 3D Gaussian Splatting."""

__version__ = "0.1.0"
