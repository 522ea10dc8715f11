"""The training loop: the method's phases, one optimiser per parameter group, callbacks,
latent updates of the heads that have latents, checkpoints.

The trainer sees the field, the image-layer heads and the loss terms only through their
interfaces (:mod:`rainyscape.components`); what acts in a phase is the method's config.
"""

from __future__ import annotations

import random
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.components import (Energy, LatentModel, LossContext, ParamGroup, RenderOutput,
                                   TrainState)
from rainyscape.config import PhaseConfig
from rainyscape.engine import snapshot
from rainyscape.engine.checkpoint import checkpoint_path, load_checkpoint
from rainyscape.engine.device import flush_denormals
from rainyscape.engine.loss_sum import compute_losses, energy_terms
from rainyscape.engine.phases import PhaseSchedule
from rainyscape.engine.pipeline import Pipeline
from rainyscape.engine.progress import ProgressBar
from rainyscape.engine.render_cache import LayerCache, RenderCache
from rainyscape.engine.run_folder import RunFolder, fitting_the_run
from rainyscape.engine.sampling import MAX_WHOLE_IMAGE_PIXELS, batch_count, gather_pixels, sample_windows
from rainyscape.errors import DataError
from rainyscape.imaging.metrics import psnr


def crop_output(output: RenderOutput | None, local: Window) -> RenderOutput | None:
    """The render's images cut to a sub-window (field-specific extras do not follow)."""
    if output is None:
        return None
    cut = {k: None if v is None else local.crop(v) for k, v in
           (("rgb", output.rgb), ("depth", output.depth), ("acc", output.acc))}
    return RenderOutput(**cut)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class Trainer:
    """Trains a pipeline in a run folder. ``evaluate`` (optional) is called every
    ``trainer.eval_every`` steps and its numbers go to the log and the progress line."""

    def __init__(self, pipeline: Pipeline, run_dir: RunFolder | Path, evaluate: Callable[[], dict] | None = None):
        self.pipeline = pipeline
        self.cfg = pipeline.config.trainer
        self.folder = run_dir if isinstance(run_dir, RunFolder) else RunFolder(run_dir)
        self.run_dir = self.folder.path
        self.device = pipeline.device
        flush_denormals(self.device)
        self.scene = pipeline.scene
        self.images = self.scene.images.to(self.device)
        self.cameras = self.scene.cameras.to(self.device)
        self.train_pool = torch.tensor(self.scene.train_indices, dtype=torch.long)
        if len(self.train_pool) == 0:
            raise DataError(f"scene {self.scene.name} has no training views")
        self.phases = PhaseSchedule.of(pipeline.config.phases, self.cfg.max_iters)
        self.generator = torch.Generator().manual_seed(self.cfg.seed)
        self.evaluate = evaluate
        self.step = 0
        self.groups = self._param_groups()
        self.optimizers = self._make_optimizers()
        # the field's hooks first, then the heads' and the loss terms' (checkpoints keep this order)
        self.callbacks = [*self.pipeline.field.callbacks(),
                          *(cb for head in self.pipeline.heads.values() for cb in head.callbacks()),
                          *(cb for _, term in self.pipeline.losses.values() for cb in term.callbacks())]
        self.batch_sizes = {name: batch_count(p.patches, p.patch_size, self.scene.width, self.scene.height)
                            for name, p in pipeline.config.phases.items()}
        # the field's last render of every view, for heads that learn on whole views
        self.render_cache = (RenderCache(len(self.images), self.scene.height, self.scene.width, self.device)
                             if any(p.head_views for p in pipeline.config.phases.values()) else None)
        # the heads' last whole-view predictions, for the single rays of phases that have them
        self.layer_caches = {head.layer: LayerCache(len(self.images), self.scene.height, self.scene.width,
                                                    device=self.device)
                             for key, head in self.pipeline.heads.items()
                             if any(key in p.heads and p.rays for p in pipeline.config.phases.values())}
        self.last_save = time.monotonic()

    # ------------------------------------------------------------------ set-up

    def _param_groups(self) -> dict[str, list[ParamGroup]]:
        """Each model's parameter groups, by pipeline key."""
        return {key: list(model.param_groups()) for key, model in self.pipeline.models().items()}

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        groups = [g for gs in self.groups.values() for g in gs]
        names = [g.name for g in groups]
        if len(set(names)) != len(names):
            raise ValueError(f"parameter group names must be unique, got {names}")
        # fused: one kernel per group instead of one per tensor (5x faster with 50k-row tensors)
        return {g.name: torch.optim.Adam(g.params, lr=g.lr, betas=g.betas, eps=g.eps, fused=True)
                for g in groups}

    def state(self, phase: str) -> TrainState:
        return TrainState(self.step, self.cfg.max_iters, phase, self.optimizers, self.device)

    def _set_lrs(self, phase: PhaseConfig) -> None:
        for key, groups in self.groups.items():
            for g in groups:
                lr = g.lr_at(self.step, self.cfg.max_iters)
                if key == "field":
                    lr = phase.field_lr if phase.field_lr is not None else lr * phase.field_lr_scale
                for pg in self.optimizers[g.name].param_groups:
                    pg["lr"] = lr

    # ------------------------------------------------------------------- steps

    def _sample(self, count: int, size: int) -> tuple[Tensor, Window, Tensor]:
        """``count`` random training views, a random ``size`` window of each (0: whole views),
        and the input's pixels there."""
        view_ids, window = sample_windows(self.train_pool, count, size, self.scene.width,
                                          self.scene.height, self.generator)
        return view_ids, window, gather_pixels(self.images, view_ids.to(self.device), window)

    def _render(self, view_ids: Tensor, window: Window) -> RenderOutput:
        """The field's render of the windows, kept in the render cache where there is one."""
        out = self.pipeline.field.render(self.cameras[view_ids], window)
        if self.render_cache is not None:
            self.render_cache.write(view_ids, window, out)
        return out

    def train_step(self) -> dict:
        name, phase = self.phases.at(self.step)
        state = self.state(name)
        self._set_lrs(phase)
        for cb in self.callbacks:
            cb.before_step(state)
        view_ids, window, target = self._sample(self.batch_sizes[name], phase.patch_size)
        self.pipeline.field.train()
        out = self._render(view_ids, window)
        heads = [self.pipeline.heads[key] for key in phase.heads]
        layers: dict[str, Tensor] = {}
        for head in heads:
            head.train()
            layers[head.layer] = head(view_ids.to(self.device), window)
        background = out.rgb.detach()
        residual = target - background
        field_layers = {h.layer: h.for_field(layers[h.layer].detach(), residual, view_ids, background)
                        for h in heads}
        ctx = LossContext(out.rgb, target, layers, out, view_ids, self.step, name, window,
                          field_layers=field_layers)
        terms = self.pipeline.loss_terms(name)
        total, values = compute_losses(terms, ctx)
        # what the terms measured on this batch (the latent updates below evaluate them again)
        measured = {f"{key}.{mk}": mv for key, (_, term) in terms.items() for mk, mv in term.metrics.items()}
        if phase.rays:  # the loss: the pixel-weighted mean over the windows and the rays
            ray_total, ray_values = self._ray_losses(name, phase, heads, terms)
            share = phase.rays / (phase.rays + out.rgb[:, 0].numel())
            total = (1 - share) * total + share * ray_total
            values.update({f"rays.{k}": v for k, v in ray_values.items()})
        if phase.head_views:
            if phase.refresh_every and self.step % phase.refresh_every == 0:
                self._refresh_cache(self.step // phase.refresh_every)
            cached_total, cached_values = self._cached_view_losses(name, phase, heads, terms)
            total = total + cached_total
            values.update({f"cached_views.{k}": v for k, v in cached_values.items()})
        # the render with every layer laid over it (what the input should look like)
        fit, field_fit = out.rgb.detach(), out.rgb.detach()
        for head in heads:
            fit = head.composite(fit, layers[head.layer].detach())
            field_fit = head.composite(field_fit, field_layers[head.layer])
        # the field's own losses fit what the layers leave of the input
        field_target = target if not layers else (target - (field_fit - out.rgb.detach())).detach()
        for key, value in self.pipeline.field.extra_losses(out, field_target).items():
            total = total + value
            values[f"field.{key}"] = value.detach()
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        total.backward()
        for cb in self.callbacks:
            cb.after_backward(state, out)
        if phase.grad_clip > 0:
            for groups in self.groups.values():
                torch.nn.utils.clip_grad_norm_([p for g in groups for p in g.params], phase.grad_clip)
        for opt in self.optimizers.values():
            opt.step()
        for head in heads:
            if isinstance(head, LatentModel):
                energy = self._energy(ctx, window, head.layer, terms)
                head.update_latents(view_ids.to(self.device), window, energy, self.generator)
        for cb in self.callbacks:
            cb.after_step(state)
        self.step += 1
        # the step's numbers in one read from the device (each read waits for its queue)
        loss, fit_psnr, *terms_read = torch.stack([total.detach().float(), psnr(fit.clamp(0, 1), target).float(),
                                                  *(v.float() for v in values.values())]).tolist()
        record = {"step": self.step, "phase": name, "loss": loss, "terms": dict(zip(values, terms_read)),
                  "psnr_input": fit_psnr}
        if measured:
            record["metrics"] = measured
        return record

    def _ray_losses(self, name: str, phase: PhaseConfig, heads: list, terms) -> tuple[Tensor, dict]:
        """The per-pixel terms on ``phase.rays`` random single rays, each head's layer read
        from its cache of whole views (a constant): the field learns, the heads do not."""
        view_ids, window, target = self._sample(phase.rays, 1)
        out = self._render(view_ids, window)
        layers = {head.layer: self.layer_caches[head.layer].read(view_ids, window, head) for head in heads}
        ctx = LossContext(out.rgb, target, layers, out, view_ids, self.step, name, window)
        return compute_losses({k: v for k, v in terms.items() if not v[1].spatial}, ctx)

    @torch.no_grad()
    def _refresh_cache(self, turn: int) -> None:
        """Render training view number ``turn`` (cyclically) whole into the render cache, the
        field in eval mode as in evaluation (eval/views.py sits above the engine)."""
        view = self.train_pool[turn % len(self.train_pool)].reshape(1)
        cameras = self.cameras[view.to(self.device)]
        window = Window.full(cameras)
        field = self.pipeline.field
        field.eval()
        self.render_cache.write(view, window, field.render(cameras, window))
        field.train()

    def _cached_view_losses(self, name: str, phase: PhaseConfig, heads: list, terms) -> tuple[Tensor, dict]:
        """The phase's loss terms on ``phase.head_views`` whole training views, with the
        field's cached render of them (detached) as the background: only the heads learn.
        The layer caches keep the predictions (for the phase's single rays)."""
        view_ids, window, target = self._sample(phase.head_views, 0)
        views = view_ids.to(self.device)
        cached = self.render_cache.read(views, window)
        layers = {head.layer: head(views, window) for head in heads}
        residual = target - cached.rgb
        for head in heads:
            if head.layer in self.layer_caches:
                part = head.for_field(layers[head.layer].detach(), residual, views, cached.rgb)
                self.layer_caches[head.layer].write(views, part)
        ctx = LossContext(cached.rgb, target, layers, cached, view_ids, self.step, name, window, record=False)
        return compute_losses(terms, ctx)

    def _energy(self, ctx: LossContext, window: Window, layer: str, terms) -> Energy:
        """The phase's loss as a function of one layer's prediction on a sub-window, with the
        render (detached) and the other layers held at this step's values."""
        base = replace(ctx, rendered=ctx.rendered.detach(), record=False)
        terms = energy_terms(terms, layer)
        last: list = []  # [sub-window, its context]: a latent update's steps share one crop and its memo

        def crop(sub: Window) -> LossContext:
            if (sub.width, sub.height) == (window.width, window.height):
                return base
            if not last or last[0] is not sub:
                local = sub.relative_to(window)
                last[:] = [sub, replace(base, rendered=local.crop(base.rendered), target=local.crop(base.target),
                                        layers={k: local.crop(v) for k, v in base.layers.items()},
                                        output=crop_output(base.output, local), window=sub, memo={})]
            return last[1]

        def energy(sub: Window, prediction: Tensor) -> Tensor:
            c = crop(sub)
            return compute_losses(terms, replace(c, layers={**c.layers, layer: prediction}))[0]

        return energy

    # ------------------------------------------------------------- checkpoints

    def _parts(self) -> snapshot.TrainingParts:
        return snapshot.TrainingParts(self.pipeline.models(), self.optimizers,
                                      {k: t for k, (_, t) in self.pipeline.losses.items()},
                                      self.callbacks, self.generator, self.render_cache, self.layer_caches)

    def save(self) -> Path:
        self.last_save = time.monotonic()
        return self.folder.save_checkpoint(self.step, snapshot.capture(self.step, self._parts()),
                                           self.cfg.keep_checkpoints)

    def load(self, path: Path | None = None) -> Path:
        """Restore the training state from ``path``, or from the newest checkpoint that reads
        (an unreadable newer one is set aside as ``*.corrupt`` with a warning). Returns the
        checkpoint used."""
        if path is None:
            path, state = self.folder.checkpoint_to_restore(self.device, set_aside=True)
        else:
            state = load_checkpoint(path, self.device)
        with fitting_the_run(path):
            snapshot.restore_models(state, self.pipeline.models())
            # Fields may change their parameter set (densification): rebuild optimisers, then load.
            self.groups = self._param_groups()
            self.optimizers = self._make_optimizers()
            snapshot.restore_rest(state, self._parts())
        self.step = int(state["step"])
        return path

    # -------------------------------------------------------------------- loop

    def _stats(self) -> dict[str, float]:
        """The field's and the heads' state numbers, keyed ``field.NAME`` and ``HEAD.NAME``."""
        parts = {"field": self.pipeline.field, **self.pipeline.heads}
        return {f"{key}.{k}": v for key, part in parts.items() for k, v in part.stats().items()}

    def _log(self, record: dict) -> None:
        self.folder.append_log(record)

    def cut_log(self) -> None:
        """Drop log records past the current step (a killed run logged steps its last
        checkpoint does not hold; they are trained again) and any torn last line."""
        self.folder.cut_log(self.step)

    def _announce_batches(self) -> None:
        for name, phase in self.pipeline.config.phases.items():
            if self.batch_sizes[name] < phase.patches and self.phases.length(name):
                w, h = self.scene.width, self.scene.height
                print(f"phases.{name}: windows of whole {w}x{h} images; {phase.patches} of them a step "
                      f"would be {phase.patches * w * h} pixels, so a step takes {self.batch_sizes[name]} "
                      f"(a batch of whole images keeps within {MAX_WHOLE_IMAGE_PIXELS} pixels)",
                      file=sys.stderr)

    def _checkpoint_due(self) -> bool:
        every, minutes = self.cfg.checkpoint_every, self.cfg.checkpoint_minutes
        return bool((every and self.step % every == 0)
                    or (minutes and time.monotonic() - self.last_save >= 60.0 * minutes))

    def train(self) -> None:
        stop = min(self.cfg.stop_at or self.cfg.max_iters, self.cfg.max_iters)
        self.cut_log()
        self._announce_batches()
        self.last_save = time.monotonic()
        progress = ProgressBar(self.step, stop, enabled=self.cfg.progress)
        last_phase = None if self.step == 0 else self.phases.at(self.step - 1)[0]
        t0 = time.time()
        try:
            while self.step < stop:
                phase = self.phases.at(self.step)[0]
                if phase != last_phase:
                    for cb in self.callbacks:
                        cb.on_phase_start(self.state(phase))
                    last_phase = phase
                record = self.train_step()
                record["time"] = round(time.time() - t0, 3)
                if self.step % self.cfg.log_every == 0 or self.step == stop:
                    record["stats"] = self._stats()
                    self._log(record)
                if (self.evaluate is not None and self.cfg.eval_every
                        and (self.step % self.cfg.eval_every == 0 or self.step == stop)):
                    ev = self.evaluate()
                    self._log({"step": self.step, "phase": phase, "eval": ev})
                    progress.eval = ev
                progress.update(self.step, record)
                if self._checkpoint_due():
                    self.save()
        except KeyboardInterrupt:
            self.save()
            progress.close()
            print(f"\ninterrupted at step {self.step}; checkpoint saved. Resume with: "
                  f"rs-train resume={self.run_dir}", file=sys.stderr)
            raise
        progress.close()
        if self.folder.newest_checkpoint() != checkpoint_path(self.folder.checkpoints, self.step):
            self.save()
        if self.step >= self.cfg.max_iters:
            for cb in self.callbacks:
                cb.after_training(self.state(self.phases.at(self.step - 1)[0]))
