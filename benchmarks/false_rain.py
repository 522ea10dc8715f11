"""Where a rain method's predicted rain falls on dry pixels, what it costs, and whether the
other views could tell it from rain (the simulator's rain layers, for this diagnosis only).

For a finished rain run (a head that predicts rain) of a scene with clean views and true rain
layers, over its training views:

- the dry pixels (true rain under 0.02 in every channel) split by the predicted rain R there,
  each bin's PSNR against the clean view, and with ``--plain RUN_DIR`` the same pixels in a
  plain field's run of the same scene (e.g. ``3dgs``): where the rain method gains or loses;
- the rain pixels, and the bright ones among them (the input at least ``BRIGHT`` above the
  clean view): how much rain the input holds there (I - clean), how much R and the residual
  I - B hold, and how much the render keeps (B - clean);
- with ``--dilate``: how much of R a neighbour vote would take away, on the false rain (R >=
  0.05 on dry pixels more than 2 px from any rain) and on the true rain's pixels. Each
  pixel is lifted to 3D with the rendered depth and projected into its ``--views`` nearest
  training views (occlusion-tested, losses/multiview_evidence.py); the vote is the
  ``--quantile`` over them of their R there, max-pooled over ``--dilate`` pixels. R less the
  vote is what stays: rain a surface shows in every view is not rain. With ``--decoy S`` the
  vote is taken against chance: less the same vote with the neighbours' R shifted by S px,
  averaged over ``--decoy-box`` px (docs/rain.md, "False rain on light rain");
- with ``--reach``: the multi-view rain evidence that ``mv-rain`` pulls R towards, with each
  neighbour's brightest within each given reach (losses/multiview_evidence.py): its mean on
  the false rain and on the true rain's pixels (next to R and the true rain there), and its
  correlation with the true rain, and with ``--reach-gain`` the term's cap of the evidence at
  the pixel by that many times it (docs/rain.md, "The neighbours' brightest within a pixel");
- with ``--field``: how much of R the field is fitted without (the rain head's ``for_field``
  at the run's end), on the false rain and on the true rain's pixels, and on the rain's pixels
  how near the render and the field's target (the input less that part) are to the clean view;
- with ``--edge``: how much of R the rain head's ``field_edge`` gate would keep at each share
  given, on the false rain and on the true rain's pixels (the darker partner up to
  EDGE_HALF_WIDTH px across the streaks, found as the head finds them; ``--edge-sides one``:
  only as far as it is darker than the one on the other side; docs/rain.md, "The field keeps
  the bright side of an edge it blurs");
- with ``--colour``: how much of R the rain head's ``field_colour`` gate would keep at each
  start given, on the false rain and on the true rain's pixels, with the rain's colour fitted
  on the run's R of at least 0.1 (imaging/colour.py; docs/rain.md, "The field fitted without the
  rain that has the rain's colour").

    python benchmarks/false_rain.py RUN_DIR [--plain RUN_DIR] [--dilate 3 5] [--quantile 0 0.5] [--decoy 8]
        [--colour 0.1 0.2] [--edge 0.25 0.5] [--edge-sides one] [--reach 0 1 2] [--reach-gain 2] [--field]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import torch
import torch.nn.functional as F

from rainyscape.cameras import Window
from rainyscape.eval.protocol import RAIN_PIXEL
from rainyscape.eval.views import render_image, view_images
from rainyscape.imaging.angles import residual_streak_angle
from rainyscape.imaging.colour import colour_weights, departure, fit_colour
from rainyscape.imaging.streaks import EDGE_SIDES, edge_weights
from rainyscape.losses.multiview_evidence import (backproject, evidence_with_reach, with_brightest,
                                                  neighbour_colours, neighbour_table, rain_evidence)
from rainyscape.postprocess.fusion import rain_mask
from rainyscape.rain.head import EDGE_HALF_WIDTH
from rainyscape.workflow import load_trained

BINS = ((0.0, 0.01), (0.01, 0.02), (0.02, 0.05), (0.05, 0.1), (0.1, float("inf")))
FALSE_RAIN = 0.05  # predicted rain at least this on a dry pixel far from rain is false rain
BRIGHT = 0.15  # a rain pixel whose input is at least this above the clean view is a bright drop


def db(squared_error: float, count: int) -> float:
    return float("nan") if count == 0 else -10.0 * torch.log10(torch.tensor(squared_error / count)).item()


def wet(v) -> torch.Tensor:
    """(H, W) the true rain's pixels."""
    return rain_mask(v.true_rain, RAIN_PIXEL, 0)[0]


def false_rain(v) -> torch.Tensor:
    """(H, W) dry pixels more than 2 px from any rain pixel where R >= FALSE_RAIN."""
    return ~rain_mask(v.true_rain, RAIN_PIXEL, 2)[0] & (v.rain.amax(0) >= FALSE_RAIN)


def vote(pooled: torch.Tensor, depth: torch.Tensor, cameras, view: int, neighbours: torch.Tensor,
         quantile: float) -> torch.Tensor:
    """The neighbours' R (3, H, W) at the 3D point each pixel of ``view`` shows (0 where fewer
    than two neighbours see it): ``pooled`` (N, 3, H, W) every view's R, max-pooled, and
    ``depth`` (N, 1, H, W) every view's rendered depth."""
    cam = cameras[[view]]
    points = backproject(cam, Window.full(cam), depth[view:view + 1])
    colours, valid = neighbour_colours(points, neighbours[view:view + 1], cameras, pooled, depth)
    votes = torch.where(valid[:, :, None], colours, torch.full_like(colours, float("nan")))
    ref = votes.nanquantile(quantile, dim=1)[0]
    return torch.where((valid.sum(1) >= 2) & torch.isfinite(ref), ref, torch.zeros_like(ref))


def print_kept(title: str, label: str, views: dict, params: list[float], weigh) -> None:
    """Print, at each of ``params``, the share of R that a gate keeps on the false rain and on
    the true rain's pixels; ``weigh(index, view, param)`` gives the gate's (H, W) weights."""
    sums = {(p, k): [0.0, 0.0] for p in params for k in ("false", "true")}
    for i, v in views.items():
        r = v.rain.amax(0)
        masks = {"false": false_rain(v), "true": wet(v)}
        for p in params:
            kept = r * weigh(i, v, p)
            for key, m in masks.items():
                sums[(p, key)][0] += float(r[m].sum()); sums[(p, key)][1] += float(kept[m].sum())
    print(f"{title}: share of R kept on false rain / on the true rain's pixels")
    for p in params:
        kept = {k: sums[(p, k)][1] / max(sums[(p, k)][0], 1e-12) for k in ("false", "true")}
        print(f"  {label} {p}: {kept['false']:.2f} / {kept['true']:.2f}")


def colour_gate(views: dict, starts: list[float]) -> None:
    """The field_colour gate at each start, with the rain's colour fitted on the run's R of at
    least 0.1 (the head's running fit, to its fixed point)."""
    rainy = torch.stack([v.rainy for v in views.values()])
    rendered = torch.stack([v.rendered for v in views.values()]).clamp(0, 1)
    strong = torch.stack([v.rain for v in views.values()]).amax(1) >= 0.1
    colour = fit_colour(rainy - rendered, rendered, strong)
    departed = {i: departure((v.rainy - v.rendered.clamp(0, 1))[None], v.rendered.clamp(0, 1)[None], colour)[0]
                for i, v in views.items()}
    print_kept(f"colour gate (the rain's colour {[round(x, 3) for x in colour.tolist()]})", "start", views, starts,
               lambda i, v, start: colour_weights(departed[i], start))


def edge_gate(views: dict, head, shares: list[float], sides: str) -> None:
    """The field_edge gate at each share (its partner on ``sides``), the streaks' direction
    found as the head finds it."""
    angles = {}
    for i, v in views.items():
        angles[i] = residual_streak_angle((v.rainy - v.rendered)[None], head.down[[i]], head.config.max_tilt)[0]
    print_kept(f"edge gate ({sides})", "share", views, shares,
               lambda i, v, share: edge_weights((v.rainy - v.rendered)[None], angles[i], EDGE_HALF_WIDTH, share,
                                                sides)[0, 0])


@torch.no_grad()
def field_share(pipeline, views: dict) -> None:
    """Print the share of R the head's ``for_field`` hands the field, on the false rain and on
    the true rain's pixels; and on the rain's pixels the PSNR of the render and of the field's
    target (the input less that part) against the clean view, and the share of the render's
    squared error there that is its mean bias."""
    head = pipeline.rain_head
    head.eval()
    sums = {"false": [0.0, 0.0], "true": [0.0, 0.0]}
    render_se, target_se, bias, count = 0.0, 0.0, torch.zeros(3), 0
    for i, v in views.items():
        part = head.for_field(v.rain[None], (v.rainy - v.rendered)[None], torch.tensor([i]), v.rendered[None])[0]
        rainy = wet(v)
        for key, m in (("false", false_rain(v)), ("true", rainy)):
            sums[key][0] += float(v.rain.mean(0)[m].sum()); sums[key][1] += float(part.mean(0)[m].sum())
        miss = (v.rendered - v.clean)[:, rainy]
        render_se += float((miss ** 2).sum()); bias += miss.sum(1); count += int(rainy.sum())
        target_se += float(((v.rainy - part - v.clean)[:, rainy] ** 2).sum())
    share = {k: b / a if a else float("nan") for k, (a, b) in sums.items()}
    print(f"the field is fitted without this share of R (for_field): false rain {share['false']:.2f} / "
          f"the true rain's pixels {share['true']:.2f}")
    if count == 0:
        return
    mean_bias = bias / count
    bias_share = float(mean_bias.pow(2).mean()) / max(render_se / (3 * count), 1e-12)
    print(f"on the rain's pixels: the render {db(render_se, 3 * count):.2f} dB (its mean bias "
          f"{mean_bias.mean():+.3f}, {100 * bias_share:.0f} % of its squared error), the field's "
          f"target I - for_field {db(target_se, 3 * count):.2f} dB")


def evidence_at_reach(views: dict, scene, reaches: list[int], gain: float, k: int) -> None:
    """Print mv-rain's evidence at each reach (with ``reach_gain`` ``gain``) on the false rain
    and the true rain's pixels."""
    images = scene.images.permute(0, 3, 1, 2).float() / 255.0
    depth = torch.full((scene.num_images, 1, scene.height, scene.width), float("nan"))
    for i, v in views.items():
        depth[i] = v.depth
    neighbours = neighbour_table(scene.cameras.centers, list(views), k)
    print("mv-rain's evidence at each reach: mean on the false rain (R there) / on the true rain's pixels "
          "(the true rain there), correlation with the true rain")
    for reach in reaches:
        stack = with_brightest(images, reach)
        sums = {"false": [0.0, 0.0, 0], "true": [0.0, 0.0, 0]}
        pairs = []
        for i, v in views.items():
            cam = scene.cameras[[i]]
            points = backproject(cam, Window.full(cam), depth[i:i + 1])
            colours, valid = neighbour_colours(points, neighbours[[i]], scene.cameras, stack, depth)
            evidence, defined = rain_evidence(images[i:i + 1], colours[:, :, :3], valid)
            if reach:
                evidence = evidence_with_reach(evidence, rain_evidence(images[i:i + 1], colours[:, :, 3:], valid)[0], gain)
            evidence = evidence[0].mean(0)
            inside = defined[0, 0]
            for key, m, layer in (("false", false_rain(v), v.rain), ("true", wet(v), v.true_rain)):
                m = m & inside
                sums[key][0] += float(evidence[m].sum()); sums[key][1] += float(layer.mean(0)[m].sum())
                sums[key][2] += int(m.sum())
            pairs.append(torch.stack([evidence[inside], v.true_rain.mean(0)[inside]]))
        corr = float(torch.corrcoef(torch.cat(pairs, 1).double())[0, 1])
        mean = {key: (a / max(n, 1), b / max(n, 1)) for key, (a, b, n) in sums.items()}
        print(f"  reach {reach}: {mean['false'][0]:.3f} ({mean['false'][1]:.3f}) / "
              f"{mean['true'][0]:.3f} ({mean['true'][1]:.3f}), {corr:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--plain", type=Path, help="a plain field's run of the same scene")
    ap.add_argument("--dilate", type=int, nargs="*", default=[], help="neighbour vote: max-pool sizes")
    ap.add_argument("--quantile", type=float, nargs="*", default=[0.5], help="neighbour vote: quantiles")
    ap.add_argument("--views", type=int, default=6, help="neighbour views")
    ap.add_argument("--decoy", type=int, default=0,
                    help="vote against chance: less the same vote with the neighbours' R shifted "
                         "by this many pixels, averaged over --decoy-box pixels (0: no decoy)")
    ap.add_argument("--decoy-box", type=int, default=15)
    ap.add_argument("--colour", type=float, nargs="*", default=[], help="field_colour gates: their starts")
    ap.add_argument("--edge", type=float, nargs="*", default=[], help="field_edge gates: their shares")
    ap.add_argument("--edge-sides", choices=EDGE_SIDES, default="either", help="... their partner's sides")
    ap.add_argument("--reach", type=int, nargs="*", default=[], help="mv-rain's evidence at these reaches (px)")
    ap.add_argument("--reach-gain", type=float, default=0.0, help="... with this reach_gain")
    ap.add_argument("--field", action="store_true", help="the share of R the field is fitted without")
    args = ap.parse_args()
    pipeline, _ = load_trained(args.run_dir, device="cpu")
    plain = load_trained(args.plain, device="cpu")[0] if args.plain else None
    scene = pipeline.scene
    if scene.clean_images is None or scene.rain_layers is None or pipeline.rain_head is None:
        raise SystemExit(f"{args.run_dir}: needs a rain head and a scene with clean views and rain layers")
    train = list(scene.train_indices)
    views = {i: view_images(pipeline, i) for i in train}
    rows = {b: [0.0, 0.0, 0] for b in (*BINS, "false")}  # squared error (method, plain), pixels
    darker = 0.0  # the render less the clean view, summed over the false rain's pixels
    all_error = 0.0  # the squared error summed over every training pixel
    amounts = {"rain": [0.0] * 4, "bright": [0.0] * 4}  # sums of I - clean, R, I - B, B - clean
    amount_pixels = dict.fromkeys(amounts, 0)
    for i, v in views.items():
        rainy = wet(v)
        added = (v.rainy - v.clean).mean(0)
        layers = (added, v.rain.mean(0), (v.rainy - v.rendered).mean(0), (v.rendered - v.clean).mean(0))
        for key, m in (("rain", rainy), ("bright", rainy & (added >= BRIGHT))):
            for k, layer in enumerate(layers):
                amounts[key][k] += float(layer[m].sum())
            amount_pixels[key] += int(m.sum())
        dry = ~rainy
        r = v.rain.amax(0)
        err = ((v.rendered - v.clean) ** 2).mean(0)
        err_plain = ((render_image(plain, i).clamp(0, 1) - v.clean) ** 2).mean(0) if plain else err
        false_pixels = false_rain(v)
        for b in rows:
            m = false_pixels if b == "false" else dry & (r >= b[0]) & (r < b[1])
            rows[b][0] += float(err[m].sum()); rows[b][1] += float(err_plain[m].sum()); rows[b][2] += int(m.sum())
        darker += float((v.rendered - v.clean).mean(0)[false_pixels].sum())
        all_error += float(err.sum())
    false = rows.pop("false")
    dry_count = sum(n for _, _, n in rows.values())
    print(f"{args.run_dir}: dry pixels by predicted rain R (share of dry pixels: PSNR{', plain run' if plain else ''})")
    for b, (e, ep, n) in rows.items():
        tail = f" / {db(ep, n):.2f}" if plain else ""
        print(f"  R in [{b[0]}, {b[1]}): {100 * n / dry_count:5.1f} %: {db(e, n):.2f}{tail}")
    total = [sum(r[k] for r in rows.values()) for k in range(2)]
    print(f"  all dry pixels: {db(total[0], dry_count):.2f}" + (f" / {db(total[1], dry_count):.2f}" if plain else ""))
    print(f"  false rain (R >= {FALSE_RAIN}, more than 2 px from rain): {100 * false[2] / dry_count:.1f} %: "
          f"{db(false[0], false[2]):.2f}" + (f" / {db(false[1], false[2]):.2f}" if plain else "")
          + f", render - clean {darker / max(false[2], 1):+.3f}, {100 * false[0] / all_error:.0f} % of the "
          "training views' squared error")
    print("rain pixels: I - clean, R, I - B, B - clean (means)")
    for key, sums in amounts.items():
        n = amount_pixels[key]
        print(f"  {key}: {n} px: " + ", ".join(f"{a / max(n, 1):.3f}" for a in sums))
    if args.field:
        field_share(pipeline, views)
    if args.colour:
        colour_gate(views, args.colour)
    if args.edge:
        edge_gate(views, pipeline.rain_head, args.edge, args.edge_sides)
    if args.reach:
        evidence_at_reach(views, scene, args.reach, args.reach_gain, args.views)
    if not args.dilate:
        return
    rain = torch.zeros(scene.num_images, 3, scene.height, scene.width)
    depth = torch.full((scene.num_images, 1, scene.height, scene.width), float("nan"))
    for i, v in views.items():
        rain[i], depth[i] = v.rain, v.depth
    neighbours = neighbour_table(scene.cameras.centers, train, args.views)
    print("neighbour vote: share of R that stays on false rain / on the true rain's pixels")
    for dilate, q in itertools.product(args.dilate, args.quantile):
        def pool(r: torch.Tensor) -> torch.Tensor:
            return F.max_pool2d(r, dilate, 1, dilate // 2) if dilate > 1 else r
        pooled, shifted = pool(rain), pool(torch.roll(rain, (args.decoy, args.decoy), (2, 3)))
        kept = {"false": [0.0, 0.0], "true": [0.0, 0.0]}
        for i, v in views.items():
            found = vote(pooled, depth, scene.cameras, i, neighbours, q)
            if args.decoy:
                chance = vote(shifted, depth, scene.cameras, i, neighbours, q)
                k = args.decoy_box
                found = (found - F.avg_pool2d(chance[None], k, 1, k // 2, count_include_pad=False)[0]).clamp_min(0)
            stays = (v.rain - found).clamp_min(0).amax(0)
            r = v.rain.amax(0)
            for key, m in (("false", false_rain(v)), ("true", wet(v))):
                kept[key][0] += float(r[m].sum()); kept[key][1] += float(stays[m].sum())
        share = {k: a[1] / a[0] if a[0] else float("nan") for k, a in kept.items()}
        print(f"  dilate {dilate}, quantile {q}: {share['false']:.2f} / {share['true']:.2f}")


if __name__ == "__main__":
    main()
