"""3D Gaussian Splatting: the field, one rasterisation entry point (tiled torch on CPU,
gsplat on CUDA), densification and ``.ply`` export."""
