"""How recent is the background a ray field's rain head learns against?

    OMP_NUM_THREADS=1 python benchmarks/render_cache_age.py --data SCENE [--marks 1000,1500,2000] [key=value ...]

Trains ``--method`` (default ``rainyscape-nerf``) on SCENE (its rainy images, as rs-train
would) and, at each mark, reports for the training views' render cache
(engine/render_cache.py: the field's last render of each pixel, which the heads of phases
with ``head_views`` learn against): the share of pixels the field never rendered, the median
age in steps of the rendered ones, and the PSNR of the cache (holes filled, as the heads read
it) against a fresh render of every third training view by the field at that step. One JSON
line at the end.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fields import build  # noqa: E402  (benchmarks/fields.py)


def main(argv=None) -> int:
    from rainyscape.cameras import Window
    from rainyscape.eval.views import render_view
    from rainyscape.imaging.metrics import psnr

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--method", default="rainyscape-nerf")
    p.add_argument("--marks", default="1000,1500,2000")
    p.add_argument("--out", default="/tmp/render_cache_age")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args(argv)
    overrides = [f"data={args.data}", "trainer.progress=false", "trainer.eval_every=0",
                 "trainer.checkpoint_every=0", *args.overrides]
    cfg, trainer = build(args.method, overrides, Path(args.out))
    cache = trainer.render_cache
    if cache is None:
        raise SystemExit(f"{args.method}: no phase learns on whole cached views (head_views)")
    written = torch.full(cache.known.shape[:3], -1, dtype=torch.long)  # the step of each pixel's last render
    write = cache.write

    def recording(view_ids, window, output):
        write(view_ids, window, output)
        xs, ys = window.pixel_grid(written.device)
        written[view_ids.to(written.device)[:, None, None].expand_as(xs), ys, xs] = trainer.step

    cache.write = recording
    views = torch.tensor(trainer.scene.train_indices)
    report = {"data": args.data, "overrides": args.overrides, "marks": {}}
    for mark in sorted(int(m) for m in args.marks.split(",")):
        while trainer.step < min(mark, cfg.trainer.max_iters):
            trainer.train_step()
        steps = written[views]
        known = steps >= 0
        scores = [float(psnr(cache.read(torch.tensor([v]), Window.full(trainer.cameras[[v]])).rgb,
                             render_view(trainer.pipeline, v).rgb)) for v in views[::3].tolist()]
        trainer.pipeline.field.train()  # render_view leaves it in eval mode
        report["marks"][trainer.step] = {
            "never_rendered": round(float((~known).float().mean()), 3),
            "median_age_steps": int((trainer.step - steps[known]).median()) if bool(known.any()) else None,
            "psnr_cache_vs_fresh": round(sum(scores) / len(scores), 2)}
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
