"""What ``rs-bench`` takes (``key=value``); plain data, so ``rs-bench --help`` stays light.
Each field's ``help`` metadata is the line ``rs-bench --help`` shows for it."""

from __future__ import annotations

from dataclasses import dataclass, field

from rainyscape.config.schema import DEVICES, PROFILES

ALL_METHODS = "nerf,robust-nerf,rainyscape-nerf,3dgs,robust-3dgs,rainyscape-3dgs"


@dataclass
class BenchOptions:
    methods: str = field(default=ALL_METHODS, metadata={"help": "comma-separated methods"})
    scenes: str = field(default="demo", metadata={"help": "a scene set (cpu: 128 px for a CPU, paper: 512 px "
                                                          "for a GPU), or comma-separated simulator presets "
                                                          "or scene folders"})
    captures: str = field(default="", metadata={"help": "scenes=real: a folder of real captures (posed "
                                                         "scenes or photo folders; default "
                                                         "$RAINYSCAPE_CAPTURES, else ../shared/data/real)"})
    dataparser: str = field(default="auto", metadata={"help": "the parser of every scene folder (auto: each "
                                                              "scene's own format, detected per scene); "
                                                              "its options: dataparser.KEY=value"})
    iters: int = field(default=0, metadata={"help": "trainer.max_iters of every cell (0: the scene set's "
                                                    "budget per field, else each method's own)",
                                            "min": 0, "max": 10_000_000})
    out: str = field(default="benchmarks/results", metadata={"help": "results folder"})
    name: str = field(default="", metadata={"help": "results name: OUT/NAME.json, OUT/NAME.md, OUT/runs/NAME "
                                                    "(default: today's date); the same command again "
                                                    "resumes it"})
    device: str = field(default="auto", metadata={"help": "the cells' device", "choices": DEVICES})
    profile: str = field(default="auto", metadata={"help": "every method's recipe (auto: gpu when the cells "
                                                           "train on CUDA)", "choices": ("auto", *PROFILES)})
    ceiling: str = field(default="auto", metadata={"help": "methods also trained on each scene's "
                                                           "clean views, at the same budget: the field's "
                                                           "ceiling (auto: nerf and 3dgs where listed; "
                                                           "none: no such rows)"})
    ablation: str = field(default="", metadata={"help": "a scene for the loss ablation table (default: none)"})
    ablation_method: str = field(default="rainyscape-nerf", metadata={"help": "the method the ablation varies"})
    scene_width: int = field(default=0, metadata={"help": "simulated scenes: image width (0: the set's or "
                                                          "preset's)", "min": 0, "max": 8192})
    scene_height: int = field(default=0, metadata={"help": "simulated scenes: image height (0: the set's, or "
                                                           "the preset's aspect ratio)", "min": 0, "max": 8192})
    scene_rows: int = field(default=0, metadata={"help": "simulated scenes: camera rows (0: the set's or "
                                                         "preset's)", "min": 0, "max": 100})
    scene_cols: int = field(default=0, metadata={"help": "simulated scenes: camera columns (0: the set's or "
                                                         "preset's)", "min": 0, "max": 100})
    scene_rain: str = field(default="static", metadata={"help": "simulated scenes: rain fixed in 3D, as a "
                                                                "camera array sees it (static), or moving "
                                                                "between views, as in a video (dynamic)",
                                                        "choices": ("static", "dynamic")})
    allow_unequal: bool = field(default=False, metadata={"help": "run methods of one field with different "
                                                                 "budgets (steps, pixels per step); the tables "
                                                                 "print the difference"})
    jobs: int = field(default=1, metadata={"help": "cells trained at the same time", "min": 1, "max": 256})
    threads: int = field(default=0, metadata={"help": "torch threads per cell (0: torch's default, "
                                                      "or cores / jobs when jobs > 1)", "min": 0, "max": 1024})
    force: bool = field(default=False, metadata={"help": "start benchmark NAME afresh: replace OUT/NAME.json, "
                                                         "OUT/NAME.md and OUT/runs/NAME (also when rs-bench did "
                                                         "not write them)"})
