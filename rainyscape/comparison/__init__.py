"""``rs-bench``: a matrix of methods x scenes at one budget, resumable, and its tables.

Every cell trains in its own subprocess (so its peak memory is its own) under
``OUT/runs/NAME/<scene>__<method>/``; the results file ``OUT/NAME.json`` is rewritten after
each cell, and a rerun of the same command skips finished cells and resumes interrupted
ones from their last checkpoint. ``OUT/NAME.md`` holds the tables: the paper's Table I
layout (per scene PSNR / SSIM / LPIPS, then the average) for de-raining at the training
views and for held-out views, with training time and peak memory, and the loss ablation
(the paper's Table II) when asked.

Modules: ``options`` (what rs-bench takes), ``scenes`` (scene specs -> folders, simulated
once into a cache), ``matrix`` (the cells), ``cell`` (one cell in a subprocess; its
``__main__``), ``results`` (the results file), ``tables`` (Markdown), ``run`` (all of it).
"""
