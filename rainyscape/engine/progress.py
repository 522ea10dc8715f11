"""The console progress line of a training run: step, phase, loss, PSNR, it/s, time left."""

from __future__ import annotations

import sys


class ProgressBar:
    """A tqdm bar (or nothing when disabled) fed with the trainer's step records."""

    def __init__(self, start: int, stop: int, enabled: bool):
        self.eval: dict = {}
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=stop, initial=start, dynamic_ncols=True, unit="it",
                            file=sys.stderr, mininterval=0.5)
        self.last = start

    def update(self, step: int, record: dict) -> None:
        if self.bar is None:
            return
        self.bar.update(step - self.last)
        self.last = step
        post = {"phase": record["phase"], "loss": f"{record['loss']:.4f}",
                "psnr(input)": f"{record['psnr_input']:.2f}"}
        for k, v in self.eval.items():
            if k.endswith("psnr_clean"):
                post[k.replace("_psnr_clean", " psnr(clean)")] = f"{v:.2f}"
        self.bar.set_postfix(post, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
