"""PSNR against training time for one method / field setting on the CLEAN images of a scene.

    python benchmarks/fields_curve.py --data SCENE --tag TAG --marks 250,500,1000,1500 [key=value ...]

Trains ``--method`` (default ``nerf``) with the given overrides for its schedule
(``trainer.max_iters``, the last mark by default) and, at every step in ``--marks``, stops the
clocks and evaluates every training and held-out view against the clean images: PSNR / SSIM.
Training wall time and process CPU time (``time.process_time``: user + sys of this process,
all its threads) are summed over training steps only (evaluation excluded). One JSON line per
run goes to ``--out/curves.jsonl``.

SCENE: a maya-csv scene with ``images_wo_rain`` (simulated: trained on the clean views, or on
the rainy ones with ``--rainy``, scored against the clean views either way), or
any other scene folder (LLFF fern: the photos are clean; pass ``dataparser.downscale=N``).
Run with ``OMP_NUM_THREADS=1`` to compare settings by CPU time on a shared machine.

    python benchmarks/fields_curve.py --plot A/curves.jsonl B/curves.jsonl --png docs/img/x.png

draws every run of the given files: training and held-out PSNR against CPU seconds, one
panel pair per scene.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fields import build, view_metrics  # noqa: E402  (benchmarks/fields.py)
from rainyscape.comparison.plan import fixed_length  # noqa: E402


def scene_overrides(data: str, rainy: bool = False) -> list[str]:
    """Train on the clean views of a simulated scene (its rainy ones with ``rainy``: scored
    against the clean views all the same); other folders are read as they are."""
    if (Path(data) / "images_wo_rain").is_dir() and not rainy:
        return ["dataparser=maya-csv", "dataparser.images=images_wo_rain", f"data={data}"]
    return [f"data={data}"]


def run(args) -> dict:
    marks = sorted(int(m) for m in args.marks.split(","))
    overrides = scene_overrides(args.data, args.rainy) + [
        "trainer.progress=false", "trainer.eval_every=0", "trainer.checkpoint_every=0",
        *fixed_length(args.iters or marks[-1]), *args.overrides]
    cfg, trainer = build(args.method, overrides, Path(args.out) / f"curve-{args.tag}")
    scene = trainer.scene
    wall = cpu = 0.0
    curve = []
    for mark in marks:
        while trainer.step < min(mark, cfg.trainer.max_iters):
            w0, c0 = time.perf_counter(), time.process_time()
            trainer.train_step()
            wall += time.perf_counter() - w0
            cpu += time.process_time() - c0
        tr_psnr, tr_ssim = view_metrics(trainer, scene.train_indices)
        point = {"step": trainer.step, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
                 "train_psnr": round(tr_psnr, 2), "train_ssim": round(tr_ssim, 4),
                 "stats": trainer.pipeline.field.stats()}
        if scene.eval_indices:
            he_psnr, he_ssim = view_metrics(trainer, scene.eval_indices)
            point.update(heldout_psnr=round(he_psnr, 2), heldout_ssim=round(he_ssim, 4))
        curve.append(point)
        print(json.dumps({"tag": args.tag, **point}), flush=True)
    result = {"tag": args.tag, "method": args.method, "scene": scene.name, "rainy": args.rainy,
              "size": [scene.width, scene.height], "threads": torch.get_num_threads(),
              "overrides": list(args.overrides), "curve": curve}
    if scene.clean_images is not None:  # the input's own score: the training images vs clean
        from rainyscape.imaging.metrics import psnr

        result["input_train_psnr"] = round(sum(float(psnr(
            scene.images[i].permute(2, 0, 1)[None].float() / 255,
            scene.clean_images[i].permute(2, 0, 1)[None].float() / 255)) for i in scene.train_indices)
            / len(scene.train_indices), 2)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "curves.jsonl", "a") as fh:
        fh.write(json.dumps(result) + "\n")
    return result


def plot(files: list[str], png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [json.loads(line) for f in files for line in Path(f).read_text().splitlines() if line.strip()]
    scenes = sorted({r["scene"] for r in runs})
    fig, axes = plt.subplots(len(scenes), 2, figsize=(10, 3.2 * len(scenes)), squeeze=False)
    for row, scene in zip(axes, scenes):
        for r in (r for r in runs if r["scene"] == scene):
            cpu = [p["cpu_s"] for p in r["curve"]]
            for ax, key in zip(row, ("train_psnr", "heldout_psnr")):
                ax.plot(cpu, [p.get(key) for p in r["curve"]], "o-", label=r["tag"])
        for ax, what in zip(row, ("training views", "held-out views")):
            ax.set(title=f"{scene}: {what}", xlabel="CPU s (1 thread)", ylabel="PSNR dB")
            ax.grid(alpha=0.3)
        row[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=90)


def main(argv: list[str]) -> int:
    if argv[:1] == ["--plot"]:
        png = argv[argv.index("--png") + 1] if "--png" in argv else "fields_curve.png"
        plot([a for a in argv[1:argv.index("--png") if "--png" in argv else None]], png)
        return 0
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--method", default="nerf")
    parser.add_argument("--tag", default="run")
    parser.add_argument("--marks", default="250,500,1000,1500", help="comma-separated steps")
    parser.add_argument("--iters", type=int, default=0, help="schedule length (0: the last mark)")
    parser.add_argument("--rainy", action="store_true", help="train on the rainy views (scored against the clean ones)")
    parser.add_argument("--out", default="outputs/benchmarks/fields")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    run(parser.parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
