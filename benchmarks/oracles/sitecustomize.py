"""Oracle training rows for the Gaussian rain methods: what a perfect rain mask or a perfect
rain layer would give at the recipe's budget (docs/rain.md, "What a perfect mask or a
perfect rain layer gives the Gaussians"). They read the simulator's true rain *in training*,
which no method may do; they bound what a method can reach, and are never a method's row.

rs-bench runs every cell in a fresh interpreter, so the oracle is put in place by this
``sitecustomize`` module on ``PYTHONPATH``, switched on by the environment (unset: nothing
changes):

- ``RS_ORACLE_MASK=T`` (with ``RS_ORACLE_DILATE=N``, 1 by default): a plain field's ``l1-ssim`` term
  leaves out the pixels where the true rain exceeds T, grown by N px (its ``pixel_weights``):
  its L1 and its SSIM map are averaged over the other pixels only. The SSIM windows of the kept pixels next to
  a streak still see it; with ``losses.photometric.ssim_weight=0`` the mask is exact.
- ``RS_ORACLE_RAIN=S``: the rain head's output is S times the true rain layer of the window
  (1: the true rain; less: a head that finds every streak but only that share of its
  amount). The head's parameters stay in the graph at weight 0, so its optimiser and latent
  updates run.
- ``RS_ORACLE_RAIN_WHERE=T`` (with ``RS_ORACLE_DILATE``): the rain head predicts as it was
  trained to, and its output is kept only where the true rain exceeds T (grown likewise): a head
  with no false rain and its own amount on the rain.

    RS_ORACLE_MASK=0.02 PYTHONPATH=benchmarks/oracles rs-bench methods=3dgs scenes=... \\
        losses.photometric.ssim_weight=0 ...
    RS_ORACLE_RAIN=1 PYTHONPATH=benchmarks/oracles rs-bench methods=rainyscape-3dgs scenes=...

The scene folders need the simulator's rain layers (``rain/``).
"""

import os

if os.environ.get("RS_ORACLE_MASK") or os.environ.get("RS_ORACLE_RAIN") or os.environ.get("RS_ORACLE_RAIN_WHERE"):
    import torch

    import rainyscape.engine.pipeline as _pipeline
    from rainyscape.postprocess.fusion import rain_mask

    _scene = {}
    _build = _pipeline.build_pipeline

    def _build_and_keep_scene(config, scene, device):
        _scene["scene"] = scene
        return _build(config, scene, device)

    _pipeline.build_pipeline = _build_and_keep_scene

    def _true_rain(view_ids, window, device):
        """(B, 3, h, w) the simulator's rain in each view's window."""
        layers = _scene["scene"].rain_layers
        if layers is None:
            raise SystemExit("oracle: the scene has no rain layers (a simulated scene is needed)")
        return window.table_values(layers, view_ids).float().to(device)

    def _wet(view_ids, window, device, threshold):
        """(B, 1, h, w) 1 where the true rain exceeds ``threshold``, grown by RS_ORACLE_DILATE px."""
        grow = int(os.environ.get("RS_ORACLE_DILATE", "1"))
        rain = _true_rain(view_ids, window, device)
        return torch.stack([rain_mask(r, threshold, grow) for r in rain]).float()

if os.environ.get("RS_ORACLE_MASK"):
    import rainyscape.losses.l1_ssim as _l1_ssim

    _threshold = float(os.environ["RS_ORACLE_MASK"])
    _weights = _l1_ssim.L1SSIM.pixel_weights

    def _dry_pixels(self, ctx):
        if self.config.with_rain:  # a rain method's term: the oracle is for plain fields
            return _weights(self, ctx)
        return 1.0 - _wet(ctx.view_ids, ctx.window, ctx.target.device, _threshold)

    _l1_ssim.L1SSIM.pixel_weights = _dry_pixels

if os.environ.get("RS_ORACLE_RAIN"):
    import rainyscape.rain.head as _head

    _scale = float(os.environ["RS_ORACLE_RAIN"])

    def _true_rain_head(self, view_ids, window):
        zero = sum(p.sum() for p in self.parameters()) * 0.0  # latents and networks, at weight 0
        return _scale * _true_rain(view_ids, window, self.view_states.device) + zero

    _head.RainPredictor.forward = _true_rain_head

if os.environ.get("RS_ORACLE_RAIN_WHERE"):
    import rainyscape.rain.head as _head

    _where = float(os.environ["RS_ORACLE_RAIN_WHERE"])
    _predict = _head.RainPredictor.forward

    def _rain_only_on_rain(self, view_ids, window):
        rain = _predict(self, view_ids, window)
        return rain * _wet(view_ids, window, rain.device, _where)

    _head.RainPredictor.forward = _rain_only_on_rain
