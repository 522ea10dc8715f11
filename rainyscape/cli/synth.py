"""rs-synth: simulate a multi-view rainy scene with ground truth (the paper's Maya layout).

Usage:
  rs-synth preset=NAME out=DIR [key=value ...]
  rs-synth --list                 presets with their scene and rain strength

Keys: rows, cols, width, height (pixels), mode=static|dynamic, trajectory=sphere|video,
seed, workers (processes; default: 1 for small jobs, else every core), force=true (write
into a non-empty folder), and any rain option: density (drops per m^3), wind_deg,
wind_azimuth_deg, wind2_deg, wind2_azimuth_deg, mix, exposure_s, brightness, opacity,
size_scale, min_width_px, min_length_px, rain_rate_mm_h, radius_min_mm, radius_max_mm,
jitter, near_clip, haze (0..1: a fog veil, separate from the rain layer), fps.
Prints the rainy-vs-clean PSNR / SSIM (the rain's strength) and the rain's coverage.
"""

from __future__ import annotations

import sys

from rainyscape.cli import run_cli

INT_KEYS = ("rows", "cols", "width", "height", "seed", "workers")
TEXT_KEYS = ("preset", "out", "mode", "trajectory")


def parse_args(argv: list[str]) -> dict:
    from rainyscape.config import coerce
    from rainyscape.errors import ConfigError
    from rainyscape.synth.params import RainConfig

    values: dict = {}
    rain_keys = RainConfig.keys()
    valid = [*TEXT_KEYS, *INT_KEYS, "force", *rain_keys]
    for arg in argv:
        if "=" not in arg:
            raise ConfigError(f"cannot read argument '{arg}': expected key=value")
        key, text = arg.split("=", 1)
        if key in TEXT_KEYS:
            values[key] = text
        elif key in INT_KEYS:
            values[key] = coerce(text, int, key)
        elif key == "force":
            values[key] = coerce(text, bool, key)
        elif key in rain_keys:
            values[key] = coerce(text, float, key)
        else:
            import difflib

            close = difflib.get_close_matches(key, valid, n=1)
            hint = f" Did you mean '{close[0]}'?" if close else ""
            raise ConfigError(f"unknown key '{key}'.{hint} Valid keys: {', '.join(valid)}")
    return values


def print_presets() -> None:
    from rainyscape.synth.params import SIM_VERSION
    from rainyscape.synth.presets import PRESETS
    from rainyscape.synth.strength import MEASURED_VERSION, PRESET_STRENGTH

    current = MEASURED_VERSION == SIM_VERSION

    def column(name: str, width: int) -> str:
        s = PRESET_STRENGTH.get(name, {}).get(width) if current else None
        return f"{s[0]:5.1f} dB / {s[1]:.3f}" if s else "not measured"

    print(f"{'preset':<9}  {'scene':<9}  {'views':<11}  {'label':<6}  {'at 128 px':<16}  {'at 512 px':<16}  "
          "description (rainy vs clean PSNR / SSIM)")
    for p in PRESETS.values():
        views = f"{p.rows}x{p.cols} {p.width}px"
        print(f"{p.name:<9}  {p.scene:<9}  {views:<11}  {p.label_db:4.0f}dB  {column(p.name, 128):<16}  "
              f"{column(p.name, 512):<16}  {p.level}: {p.description}")


def main(argv: list[str]) -> int:
    from rainyscape.errors import ConfigError

    flags = {a for a in argv if a.startswith("-")}
    unknown_flags = flags - {"--help", "-h", "--list"}
    if unknown_flags:
        raise ConfigError(f"unknown option {sorted(unknown_flags)[0]}; see rs-synth --help")
    if "--help" in flags or "-h" in flags:
        print(__doc__.strip())
        return 0
    if "--list" in flags:
        print_presets()
        return 0
    values = parse_args([a for a in argv if not a.startswith("-")])
    if "out" not in values:
        raise ConfigError("where to write? e.g. rs-synth preset=demo out=data/demo (rs-synth --list shows presets)")
    import json
    import time
    from pathlib import Path

    from rainyscape.synth import generate

    preset = values.pop("preset", "demo")
    out = values.pop("out")

    def progress(done: int, total: int) -> None:
        print(f"\r  rendering view {done}/{total}", end="" if done < total else "\n", flush=True)

    start = time.perf_counter()
    path = generate(out, preset, progress=progress, **values)
    info = json.loads((Path(path) / "scene.json").read_text())
    m = info["metrics"]
    print(f"wrote {info['rows'] * info['cols']} views ({info['width']}x{info['height']}, {info['mode']} rain, "
          f"{info['drops']} drops) to {path} in {time.perf_counter() - start:.1f} s")
    print(f"rainy vs clean: PSNR {m['psnr_rainy_vs_clean']:.2f} dB, SSIM {m['ssim_rainy_vs_clean']:.4f} "
          f"(per view: {min(v['psnr'] for v in m['per_view']):.2f} to {max(v['psnr'] for v in m['per_view']):.2f} dB)")
    print(f"rain streaks cover {100 * m['rain_coverage']:.1f} % of the pixels (alpha > 0.02); their per-image "
          f"mean is {100 * m['rain_mean_share']:.1f} % of their squared error")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
