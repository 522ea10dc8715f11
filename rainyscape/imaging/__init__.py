"""The bottom layer: image maths shared by losses, rain, engine, evaluation and the simulator.

Pure functions on float image tensors (B, C, H, W) in [0, 1]: metrics (PSNR, SSIM),
derivative operators (gradients, steered directional derivatives), grey levels, and the
orientation histogram that estimates rain angles. Nothing here imports another
``rainyscape`` layer.
"""
