"""Components that compose the field layer's public functions: DeSplat's per-view distractor
Gaussians (an image-layer head rendered with the Gaussian rasteriser) and their density
control. A layer above the components (it imports ``fields``), below the engine."""
