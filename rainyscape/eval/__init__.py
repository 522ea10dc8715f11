"""Evaluation of a trained pipeline, one job a module:

- ``metric_keys``: the one schema of every metric key (measures, which images and views);
- ``views``: render a view, predict its rain tile by tile, the per-view image bundle
  (``ViewImages``), and ``quick_eval`` (the PSNR curves logged during training);
- ``protocol``: per-view metrics, ``evaluate_pipeline``, ``write_metrics`` (``metrics.json``);
- ``summary``: per-view rows -> the ``summary`` means; ``rain_stats``: streak angles of rain
  maps and their correlation with the true rain; ``perceptual``: LPIPS from local weights;
- ``report``: ``report.html``; ``images``: tensors -> pictures (colour maps, strips);
- ``run_renders`` (rs-render's images and video), ``camera_path``, ``embedding`` (the paper's
  Fig. 8), ``export`` (rs-export's meshes, 3DGS .ply and transforms.json).

Layering: eval imports the engine and below, never ``rainyscape.comparison`` or ``rainyscape.cli``.
"""
