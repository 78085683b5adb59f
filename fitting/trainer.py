"""The fit loop: mask-guided ray batches, colour + mask loss, Adam with per-step decay, resumable checkpoints."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.averaging import WeightAverage
from fitting.checkpoint import save_checkpoint
from fitting.config import FitConfig
from fitting.corrections import CameraColour, FrameAppearance, MeasuredColour, PoseCorrection, PosePrior, RowAdam
from fitting.data import FitData
from fitting.distributed import SINGLE, Processes, agreed_max, any_process, sum_gradients
from fitting.files import named_errors
from fitting.losses import batch_loss, structure_term
from fitting.model_setup import encoding_window, make_field
from fitting.plots import write_curve, write_validation
from fitting.run_folder import add_to_last_row, trim_log, write_config
from fitting.schedule import Budget, lr_factor
from fitting.selection import paired_error_db, selection_set
from fitting.training_rays import RaySet, render_ray_sets
from fitting.unseen import VirtualTerm, mirror_terms, outline_terms, terms_value, unseen_terms
from narf.fields.common import PoseBatch
from narf.grids import grid_smoothness, random_vertices
from narf.metrics import psnr
from narf.occupancy import refresh_cells


@dataclass
class FitResult:
    run_dir: Path
    step: int
    loss: float
    psnr: float
    finished: bool
    kept: tuple[int, float] | None = None  #: with held-back frames: the best step and its score (fitting.selection)


class TrainingDiverged(ValueError):
    """The training loss stopped being finite; the message names the run folder, the step and the checkpoint kept."""


class Trainer:
    """Model and optimiser for ``config`` in ``run_dir``, trained on ``data``; ``state`` (a loaded checkpoint)
    resumes where it stopped. ``pipelines.runs.fit.start_run`` builds one for a run of any kind."""

    def __init__(
        self,
        config: FitConfig,
        run_dir: Path,
        device: torch.device,
        data: FitData,
        state: dict | None = None,
        progress: bool = True,
        processes: Processes = SINGLE,
    ):
        self.config, self.run_dir, self.device = config, Path(run_dir), device
        self.processes, self.progress = processes, progress and processes.is_main
        # Adam's first steps move each weight by about lr * sign(gradient), so even rounding-level differences
        # between runs (CPU kernels that sum in thread order, e.g. index_add) grow to 1e-2 within a few steps
        torch.use_deterministic_algorithms(config.train.deterministic, warn_only=True)
        # that mode also fills every new tensor with NaN, a guard against kernels that read memory they never wrote
        # (about 1 % of a CPU step); no kernel of the fit does (it allocates no uninitialised tensors), and the
        # resume tests compare whole runs
        torch.utils.deterministic.fill_uninitialized_memory = False
        # subnormal floats (below 1.2e-38) become 0 on the CPU: behind a learned surface the transmittance, and with
        # it the gradients of the samples there, underflows into that range, where x86 kernels run several times
        # slower (docs/design.md, "Subnormal numbers"); no value that the fit can resolve changes. The mode is per
        # thread: here it reaches this thread; the commands set it before torch starts its worker threads
        torch.set_flush_denormal(True)
        # TensorFloat-32 matmuls (10-bit mantissa inputs, float32 sums) on CUDA only; set either way, so that a fit
        # in the same process after a tf32 one runs in float32 again (cuDNN's convolutions keep torch's default)
        torch.backends.cuda.matmul.allow_tf32 = config.train.precision == "tf32"
        torch.manual_seed(config.train.seed)
        np.random.seed(config.train.seed)
        random.seed(config.train.seed)
        # views: the training views the rays are drawn from; fit_data: everything the fit was given (views,
        # frames, boxes, validation, provenance)
        self.views, self.frames = data.training, data.frames
        self.fit_data = data
        self.field = make_field(config).to(device)
        grid = getattr(self.field, "occupancy", None)
        # the occupancy refresh's order of cells: a fixed permutation per fit (refresh_occupancy)
        generator = torch.Generator().manual_seed(config.train.seed)
        self._cell_order = None if grid is None else torch.randperm(grid.density.numel(), generator=generator)
        if state is None and hasattr(self.field, "set_boxes"):
            self.field.set_boxes(data.boxes[0].to(device), data.boxes[1].to(device))
            if data.shells is not None:
                self.field.set_shells(data.shells)
        if config.train.compile:
            # compile the bound forward, not the module, so state_dict keys stay those of the eager field
            self.field.forward = torch.compile(self.field.forward, dynamic=True)
        self._build_extra_modules()
        self._build_corrections(data)
        self.selection = (
            None
            if data.selection is None
            else selection_set(data.selection, config.train.select_rays, config.train.select_margin)
        )
        decay = config.train.ema_decay  # the weights' moving average (fitting.averaging), from the initial weights
        self.average = WeightAverage(self.field, decay) if decay else None
        self.rays_per_step = config.train.images_per_step * config.train.rays_per_image
        # fused: one kernel for all parameters (0.25 against 0.99 ms a CPU-preset step; same update rule)
        groups = self._parameter_groups() + self._correction_groups()
        self.optimiser = torch.optim.Adam(
            groups, lr=config.train.lr, betas=(0.9, config.train.adam_beta2), eps=config.train.adam_eps, fused=True
        )
        self.budget = Budget(config.train.steps)  # steps only until fit() gives it its minutes
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimiser, lambda step: self._lr_factor(step))
        self.pose_optimiser = self.pose_scheduler = None
        if self.pose_correction is not None and config.train.pose_correction:  # per-knot moments (RowAdam)
            self.pose_optimiser = RowAdam(self._pose_groups(), lr=config.train.pose_lr, eps=config.train.adam_eps)
            self.pose_scheduler = torch.optim.lr_scheduler.LambdaLR(
                self.pose_optimiser, lambda step: self._lr_factor(step)
            )
        self.generator = torch.Generator(device="cpu").manual_seed(config.train.seed + 1)
        self.step, self.elapsed = 0, 0.0
        self._saved_step, self._diverged = None, False  # the step of the last checkpoint written; a finite-loss stop
        if state is not None:
            self._restore(state)
            self._saved_step = self.step
            if processes.is_main:  # the killed process's rows past its checkpoint would repeat steps
                trim_log(self.run_dir / "log.jsonl", self.step)
        if processes.is_main:  # the config as run (resumed runs: with their overrides), the one place it is written
            write_config(self.run_dir, config)

    def _build_extra_modules(self) -> None:
        """Subclasses add trained modules here (after the seed, before the optimiser)."""

    def _build_corrections(self, data: FitData) -> None:
        """The input corrections the config asks for (``fitting.corrections``; both start at zero and draw no
        random numbers, so the field's initialisation is the same with or without them)."""
        t = self.config.train
        self.pose_correction = self.camera_colour = None
        if t.pose_correction and data.capture_poses is None:
            raise ValueError("train.pose_correction: this data has no body parameters to correct")
        if data.capture_poses is not None:  # corrected while fitting, or refined against the masks: the run keeps them
            self.pose_correction = PoseCorrection(data.capture_poses, t.pose_knot_every).to(self.device)
        if t.pose_correction:  # the pose's gradient through the smooth bands only (docs/model.md §6)
            self.field.pose_gradient_freqs = t.pose_gradient_freqs
        if t.camera_colour:
            self.camera_colour = CameraColour(data.training.n_cameras).to(self.device)
        self.colour_response = self.camera_colour  # the measured gains, then the learned transform (either or both)
        if data.camera_gains is not None:
            self.colour_response = MeasuredColour(data.camera_gains, self.camera_colour).to(self.device)
        self.frame_appearance = None
        if self.config.model.appearance_dim:
            n_frames = self.views.poses.reach.shape[0]
            self.frame_appearance = FrameAppearance(n_frames, self.config.model.appearance_dim).to(self.device)

    def _correction_groups(self) -> list[dict]:
        """Optimiser groups of the input corrections, each with its own learning rate (decayed as the field's)."""
        t, groups = self.config.train, []
        if self.camera_colour is not None:
            groups.append({"params": list(self.camera_colour.parameters()), "lr": t.colour_lr})
        if self.frame_appearance is not None:  # as the field's weights (NeRF-W)
            groups.append({"params": list(self.frame_appearance.parameters()), "lr": t.lr})
        return groups

    def _pose_groups(self) -> list[dict]:
        """The pose correction's parameter groups: turns (radians) at ``train.pose_lr``, the shift (metres) at
        ``train.pose_shift_lr``."""
        c, t = self.pose_correction, self.config.train
        return [{"params": [c.joints, c.root], "lr": t.pose_lr}, {"params": [c.shift], "lr": t.pose_shift_lr}]

    def _correction_state(self) -> dict:
        """The corrections' part of the checkpoint."""
        return {name: module.state_dict() for name, module in self._correction_modules().items()}

    def correcting_poses(self) -> bool:
        """Whether this step's poses are the photometric correction's (``train.pose_correction``, from
        ``train.pose_start``); otherwise the training views' own (the capture's, refined against the masks)."""
        t = self.config.train
        return self.pose_correction is not None and t.pose_correction and self.step >= t.pose_start

    def poses_at(self, index: torch.Tensor | None = None, grad: bool = True) -> PoseBatch:
        """The PoseBatch of training frames ``index`` (all when None): corrected once ``train.pose_start`` is
        reached, else the capture's. ``grad`` False: without gradient (occupancy refreshes, validation)."""
        base = self.views.poses
        if index is None:
            index = torch.arange(base.reach.shape[0], device=self.device)
        if not self.correcting_poses():
            return base.select(index)
        with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
            return self.pose_correction.pose_batch(index, base)

    def correction_penalty(self, frames: torch.Tensor | None = None) -> torch.Tensor | float:
        """The pulls of the active corrections towards zero (``fitting.corrections``), summed; the pose pull over the
        training frames ``frames`` (those of the step)."""
        t, total = self.config.train, 0.0
        if self.correcting_poses():
            prior = PosePrior(t.pose_prior, t.pose_prior_degrees, t.pose_prior_cm, t.pose_smooth)
            total = total + self.pose_correction.penalty(prior, frames)
        if self.camera_colour is not None:
            total = total + self.camera_colour.penalty(t.colour_prior)
        if self.frame_appearance is not None:
            total = total + self.frame_appearance.penalty(t.appearance_decay)
        return total

    def _parameter_groups(self) -> list[dict]:
        """Optimiser parameter groups; the field's use ``train.lr``, its part grids' tables (``model.encoding``
        grid) ``train.grid_lr`` and ``train.grid_decay`` (docs/model.md §2, *Part grids*)."""
        grids = getattr(self.field, "grids", None)
        if grids is None:
            return [{"params": list(self.field.parameters())}]
        tables = {id(p) for p in grids.parameters()}
        t = self.config.train
        return [
            {"params": [p for p in self.field.parameters() if id(p) not in tables]},
            {"params": list(grids.parameters()), "lr": t.grid_lr, "weight_decay": t.grid_decay},
        ]

    def _extra_state(self) -> dict:
        """Subclasses' additions to the checkpoint."""
        return {}

    def _validation_latent(self, item: tuple) -> torch.Tensor | None:
        """The autoencoder code of a validation item (None for per-subject fits)."""
        return None

    def _restore(self, state: dict) -> None:
        self.field.load_state_dict(state["model"])
        if self.average is not None:
            if "weight_average" not in state:
                raise ValueError("the checkpoint has no weight average (fitted with train.ema_decay 0; fit anew)")
            self.average.restore(state["weight_average"])
        if self.selection is not None and state.get("selection") is not None:
            self.selection.restore(state["selection"])
        for name, module in self._correction_modules().items():
            if name not in state:
                raise ValueError(f"the checkpoint has no {name} (written by an earlier version; fit anew)")
            module.load_state_dict(state[name])
        self.optimiser.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(state["rng"]["sampler"])
        torch.set_rng_state(state["rng"]["torch"])
        self.step, self.elapsed = state["step"], state.get("elapsed", 0.0)

    def _correction_modules(self) -> dict:
        """The input corrections and their optimiser, by their checkpoint keys (those in use)."""
        modules = {
            "pose_correction": self.pose_correction,
            "camera_colour": self.camera_colour,
            "frame_appearance": self.frame_appearance,
            "pose_optimizer": self.pose_optimiser,
            "pose_scheduler": self.pose_scheduler,
        }
        return {name: module for name, module in modules.items() if module is not None}

    def checkpoint(self) -> None:
        """Save the run's state; never after the loss stopped being finite (the last good checkpoint stays)."""
        if not self.processes.is_main or self._diverged:  # every process holds the same weights; one writes them
            return
        save_checkpoint(
            self.run_dir,
            {
                "config": self.config.to_dict(),
                "step": self.step,
                "elapsed": self.elapsed,
                "world_size": self.processes.world_size,  # run state: the processes that fitted it (not a setting)
                "model": self.field.state_dict(),
                "optimizer": self.optimiser.state_dict(),
                "scheduler": self.scheduler.state_dict(),
                "frames": self.frames,
                "provenance": self.fit_data.provenance,
                "rng": {"sampler": self.generator.get_state(), "torch": torch.get_rng_state()},
                **self._correction_state(),
                **self._extra_state(),
                **({} if self.selection is None else {"selection": self.selection.state()}),
                **({} if self.average is None else {"weight_average": self.average.state()}),
            },
        )
        self._saved_step = self.step

    def _check_finite(self, loss: float) -> None:
        """Stop with ``TrainingDiverged`` once the loss is NaN or infinite on any process (its weights are then
        no longer finite, so nothing more is saved)."""
        if any_process(not math.isfinite(loss), self.processes, self.device):
            self._diverged = True
            saved = self._saved_step
            kept = "no checkpoint was written" if saved is None else f"kept the checkpoint of step {saved}"
            raise TrainingDiverged(
                f"{self.run_dir}: the training loss became {loss} at step {self.step}; {kept}. Try a lower train.lr"
            )

    def train_step(self) -> tuple[float, float]:
        """One step on the global batch; each process renders its share (``fitting.distributed``)."""
        t, r = self.config.train, self.config.render
        with torch.profiler.record_function("narf.sample"):  # named ranges for profiles (bench/gpu_real.py)
            batch = self.views.sample(
                t.images_per_step,
                t.rays_per_image,
                t.body_fraction,
                t.border_fraction,
                self.generator,
                t.views_per_frame,
            )
        n = batch.origins.shape[0]
        self.field.point_window = encoding_window(self.config, self.step)
        uniforms = [torch.rand(n, k, generator=self.generator).to(self.device) for k in (r.train_coarse, r.train_fine)]
        backgrounds = None
        if t.random_background:
            backgrounds = torch.rand(n, 3, generator=self.generator).to(self.device)
        poses, index = self.views.poses, None
        if self.correcting_poses():  # only the frames this batch draws
            index, batch.frames = torch.unique(batch.frames, return_inverse=True)
            poses = self.poses_at(index)
        if self.frame_appearance is not None:  # training rays only: evaluation reads the zero code
            poses = self.frame_appearance.attach(poses, index)
        share = self.processes.share(n)
        my_backgrounds = None if backgrounds is None else backgrounds[share]
        with self.autocast(), torch.profiler.record_function("narf.forward"):
            mine = batch.take(share)
            training = RaySet(mine.origins, mine.dirs, mine.frames, poses, [u[share] for u in uniforms])
            terms = self.virtual_terms(poses, batch.frames, index)  # every process draws and renders the same
            # one render of the training rays and every term's virtual rays (docs/results/benchmark.md)
            out = render_ray_sets(
                self.config, self.field, [training, *(s for t in terms for s in t.sets)], r.train_coarse, r.train_fine
            )
            loss, colour = batch_loss(
                self.config,
                out[0],
                mine,
                normalisers=(3 * n, batch.mask_weight.sum().clamp_min(1)),
                camera_colour=self.colour_response,
                backgrounds=my_backgrounds,
            )
            loss = loss + terms_value(terms, out[1:]) / self.processes.world_size
            if t.s3im_weight:  # over this process's rays (docs/model.md §6)
                term = structure_term(self.config, out[0], mine, self.generator, self.colour_response, my_backgrounds)
                fade = 1.0 - self.budget.progress(self.step) if t.s3im_fade else 1.0
                loss = loss + fade * term / self.processes.world_size
        # every process adds the penalty; the summed gradients then hold it once
        loss = loss + (self.correction_penalty(index) + self.grid_penalty()) / self.processes.world_size
        return self.optimise(loss, colour)

    def grid_penalty(self) -> torch.Tensor | float:
        """``train.grid_smoothness`` times the part grids' total variation at ``train.grid_smooth_points`` random
        vertices a level (``narf.grids.grid_smoothness``); 0 without grids or with the weight 0."""
        grids, t = getattr(self.field, "grids", None), self.config.train
        if grids is None or not t.grid_smoothness:
            return 0.0
        vertices, axis = random_vertices(grids.shape, grids.n_parts, t.grid_smooth_points, self.generator, self.device)
        return t.grid_smoothness * grid_smoothness(grids.table, grids.shape, vertices, axis)

    def virtual_terms(self, poses: PoseBatch, frames: torch.Tensor, index: torch.Tensor | None) -> list[VirtualTerm]:
        """The step's terms on virtual rays (``fitting.unseen``), drawn after the training rays': the unseen views'
        around the frames ``frames`` of ``poses``, and the colour's symmetry around the capture's poses and their
        mirror images (docs/model.md §6), by training frame (``index`` maps a corrected batch's frames to them), and
        the bodies' outlines from virtual cameras."""
        drawn = frames if index is None else index[frames]
        mirrored = getattr(self.fit_data, "mirrored_poses", None)  # subject fits only
        unseen = unseen_terms(self.config, poses, frames, self.generator)
        symmetry = mirror_terms(self.config, self.views.poses, mirrored, drawn, self.generator)
        outlines = getattr(self.fit_data, "outline_rays", None)  # subject fits only
        return unseen + symmetry + outline_terms(self.config, outlines, self.views.poses, self.generator)

    def autocast(self):
        """bf16 autocast of a training forward pass when ``train.precision`` is bf16 (a no-op for fp32)."""
        enabled = self.config.train.precision == "bf16"
        return torch.autocast(torch.device(self.device).type, dtype=torch.bfloat16, enabled=enabled)

    def optimise(self, loss: torch.Tensor, colour: torch.Tensor) -> tuple[float, float]:
        """One optimiser and schedule step on ``loss`` (gradients summed over processes); returns (loss, PSNR of
        the colour MSE), summed over processes."""
        self.optimiser.zero_grad(set_to_none=True)
        if self.pose_optimiser is not None:
            self.pose_optimiser.zero_grad(set_to_none=True)
        with torch.profiler.record_function("narf.backward"):
            loss.backward()
        sum_gradients(self._trained_parameters(), self.processes)
        self.optimiser.step()
        self.scheduler.step()
        if self.average is not None:
            self.average.update(self.field)
        if self.pose_optimiser is not None:
            self.pose_optimiser.step()
            self.pose_scheduler.step()
            self.pose_correction.centre()
        self.step += 1
        self.refresh_occupancy()
        values = torch.stack([loss.detach(), colour.detach()])
        if self.processes.distributed:
            torch.distributed.all_reduce(values)
        return float(values[0]), float(psnr(values[1]))

    def _occupancy_row(self) -> dict:
        grid = getattr(self.field, "occupancy", None)
        row = {} if grid is None else {"occupied": round(grid.occupied_fraction(), 4)}
        if self.pose_optimiser is not None:
            row.update({k: round(v, 4) for k, v in self.pose_correction.magnitude().items()})
        return row

    def refresh_occupancy(self) -> None:
        """Every ``render.occupancy_every`` steps, measure the next 1/``occupancy_rounds`` of the occupancy cells (a
        fixed permutation, jitter and frames seeded by the step, so resumed and data-parallel fits agree)."""
        grid, r = getattr(self.field, "occupancy", None), self.config.render
        if grid is None or self.step % r.occupancy_every:
            return
        seed = self.config.train.seed
        round_index = (self.step // r.occupancy_every) % r.occupancy_rounds
        cells = self._cell_order.chunk(r.occupancy_rounds)[round_index].to(self.device)
        poses, field = self.poses_at(grad=False), self.field
        up = torch.tensor([[0.0, 0.0, 1.0]], device=self.device)

        def density(points: torch.Tensor, frame: int) -> torch.Tensor:  # the points as one ray of many samples
            return field.density(points[None], up, poses.select(torch.tensor([frame], device=self.device)))[0]

        generator = torch.Generator().manual_seed(seed * 1_000_003 + self.step)
        refresh_cells(grid, density, poses, field.box_centres, field.box_half_extents, cells, generator)

    def _lr_factor(self, step: int) -> float:
        """The learning rate's multiplier at ``step`` (``fitting.schedule.lr_factor``; docs/model.md §6)."""
        t = self.config.train
        progress = self.budget.progress(step)
        return lr_factor(step, progress, t.lr_decay, t.lr_min / t.lr, t.lr_anneal, t.lr_anneal_to)

    def _trained_parameters(self) -> list[torch.nn.Parameter]:
        optimisers = [self.optimiser] + ([] if self.pose_optimiser is None else [self.pose_optimiser])
        return [p for o in optimisers for group in o.param_groups for p in group["params"]]

    def fit(self, max_minutes: float | None = None) -> FitResult:
        """Train until ``train.steps`` or the time budget; checkpoints periodically and at the end."""
        t = self.config.train
        log_path = self.run_dir / "log.jsonl"
        start, last_save = time.perf_counter(), time.perf_counter()
        elapsed0, loss, score = self.elapsed, math.nan, math.nan
        bar = tqdm(total=t.steps, initial=self.step, desc="fit", unit="step", disable=not self.progress)
        self.budget = Budget(t.steps, max_minutes)
        agree = functools.partial(agreed_max, processes=self.processes, device=self.device)
        window_start, window_rays = time.perf_counter(), 0
        finished = self.step >= t.steps
        try:
            while self.step < t.steps:
                self.budget.tick(agree)
                if self.budget.out_of_time:
                    break
                loss, score = self.train_step()
                self._check_finite(loss)
                window_rays += self.rays_per_step
                self.elapsed = elapsed0 + time.perf_counter() - start
                bar.update()
                selected = self._select(self.step % t.select_every == 0 or self.step == t.steps)
                if self.processes.is_main and (self.step % t.log_every == 0 or self.step == t.steps or selected):
                    rate = window_rays / max(time.perf_counter() - window_start, 1e-9)
                    window_start, window_rays = time.perf_counter(), 0
                    bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{score:.2f}", rays_s=f"{rate:,.0f}")
                    self._log_row(log_path, {"loss": loss, "psnr": score, "rays_per_s": rate, **selected})
                if self.processes.is_main and t.validate_every and self.step % t.validate_every == 0:
                    self.validate()
                if (time.perf_counter() - last_save) / 60 >= t.checkpoint_minutes:
                    self.checkpoint()
                    last_save = time.perf_counter()
            finished = self.step >= t.steps
            # the last step is scored too when the time budget ends the fit, and its score is logged
            last = self._select(True)
            if last and not add_to_last_row(log_path, self.step, last):
                self._log_row(log_path, {"loss": loss, "psnr": score, **last})
        finally:
            bar.close()
            self.checkpoint()
            if self.processes.is_main:
                write_curve(log_path, self.run_dir / "curve.png")
        chosen = self.selection is not None and t.keep == "best"
        kept = (self.selection.best_step, self.selection.best_psnr) if chosen else None
        return FitResult(self.run_dir, self.step, loss, score, finished, kept)

    def _log_row(self, log_path: Path, values: dict) -> None:
        """Append one row of ``log.jsonl``: the step, ``values`` and the run's state."""
        row = {
            "step": self.step,
            **values,
            "lr": self.scheduler.get_last_lr()[0],
            "elapsed_s": self.elapsed,
            "world_size": self.processes.world_size,
            **self._occupancy_row(),
        }
        with named_errors(log_path), open(log_path, "a") as handle:
            handle.write(json.dumps(row) + "\n")

    def _select(self, due: bool) -> dict:
        """When ``due`` and the fit holds frames back, score them (``fitting.selection``; once per step) and keep the
        weights if they are the best or within ``train.select_margin`` of it: the log's ``select_psnr``,
        ``select_se_db`` (the paired standard error against the best score so far,
        ``fitting.selection.paired_error_db``) and ``best_step``, else {}. With ``train.ema_decay`` the weights
        scored and kept are the average (``fitting.averaging``), and the raw weights' score is logged
        beside as ``select_psnr_raw``."""
        if not due or self.selection is None or not self.processes.is_main:
            return {}
        if self.selection.history and self.selection.history[-1][0] == self.step:
            return {}
        raw = {}
        if self.average is not None:
            raw = {"select_psnr_raw": self.selection.score(self.config, self.field, self.colour_response)}
        with self.kept_weights():
            errors = self.selection.errors(self.config, self.field, self.colour_response)
            spread = paired_error_db(errors, self.selection.leader_errors)
            self.selection.update(self.step, errors, self.field)
        score = self.selection.history[-1][1]
        return {"select_psnr": score, "select_se_db": spread, **raw, "best_step": self.selection.best_step}

    def kept_weights(self):
        """A block in which the field holds the weights a run is evaluated with: the average with
        ``train.ema_decay``, else its own."""
        return contextlib.nullcontext() if self.average is None else self.average.applied(self.field)

    def validate(self) -> Path | None:
        """Render one held-out view (a training pose from a test camera) next to its ground truth."""
        if self.fit_data.validation is None:
            return None
        item = self.fit_data.validation()
        image, camera, pose = item[:3]
        if self.fit_data.validation_frame is not None:  # the frame's corrected pose once the poses are corrected
            pose = self.poses_at(torch.tensor([self.fit_data.validation_frame], device=self.device), grad=False)
        self.field.eval()
        with self.kept_weights():
            path = write_validation(
                self.field,
                self.config,
                image,
                camera,
                pose.to(self.device),
                self.run_dir / "val" / f"step_{self.step:07d}.png",
                self._validation_latent(item),
            )
        self.field.train()
        return path
