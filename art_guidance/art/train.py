"""Training loop of `art-guidance train`: AdamW, early stopping, atomic checkpoints, resume.

Two files are written (atomically, by rank 0) at every validation pass:

* ``OUT``: the inference checkpoint with the best weights so far (lowest validation loss), the
  config, the normalisation statistics, the dataset manifests' sha256 and the training command;
* ``OUT.state``: the full training state (last weights, best weights, optimiser, step,
  early-stopping counters, history). Running the same command again resumes from it after a
  kill; since every random draw (batch order, suffix starts, dropout) derives from the seed and
  the step, the resumed run reaches the weights of an uninterrupted one.

``OUT.lock`` is held (flock) while a run trains, so two runs never write the same files.

The loss is the paper's control + next-state MSE (teacher forcing) on normalised features, the
validation loss the same on a seeded share of the training split (the dataset's test split is
never read); both run over the steps of `data.valid_mask` (for DAgger rows, the nodes from
their `train_from` on), which also gives the counts they are divided by. Learning rate:
linear warm-up, then cosine decay to ``min_lr_ratio * lr`` over ``max_epochs``; gradient-norm
clipping 1.0. Data parallel under torchrun (`distributed`). The lock and the signals are
`train_control`, the checks of a fine-tuning's initial model `finetune`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from tqdm import tqdm

from art_guidance import __version__
from art_guidance.art import checkpoint
from art_guidance.art.config import preset
from art_guidance.art.data import (
    epoch_order, load_training_data, make_batch, suffix_starts, trained_manifests,
    trained_seed_bases, valid_mask, validation_starts,
)
from art_guidance.art.distributed import DistContext, init_distributed, shutdown_distributed
from art_guidance.art.finetune import (
    check_init_data as _check_init_data, initial_model as _initial_model,
)
from art_guidance.art.model import ArtModel, combined_loss, loss_counts, loss_terms
from art_guidance.art.train_control import StopOnSignal, exclusive
from art_guidance.errors import InputError

STATE_SUFFIX = ".state"


@dataclass(frozen=True)
class TrainOptions:
    """What `art-guidance train` was asked to do.

    Attributes:
        data: dataset directories (their train splits).
        out: inference checkpoint path (the training state goes to ``out + ".state"``).
        preset: "small" (default), "paper" or "tiny" (tests).
        representation: "roe" or "rtn".
        seed: seeds the initial weights, the validation split and every batch draw.
        max_minutes: stop (resumable) after this much wall time in this invocation.
        max_steps: stop (resumable) at this optimiser step (smoke runs and tests).
        overrides: TrainConfig fields to change (e.g. {"batch_size": 32}).
        model_overrides: ArtConfig fields to change (e.g. {"normalization": "timestep"}).
        progress: show a progress bar.
        device: "cpu" or "cuda" (default: CUDA when available).
        command: the command line, stored in the checkpoint.
        init: a trained checkpoint to start from (fine-tuning): its weights and its
            normalisation statistics are kept; the preset, representation and model
            overrides must describe it, and the data must be of its dataset's mode and
            configuration. Its validation loss on this run's validation split is the best
            to beat (step 0), so OUT is the initial model if training never improves on it.
    """

    data: tuple[str, ...]
    out: str
    preset: str = "small"
    representation: str = "roe"
    seed: int = 0
    max_minutes: float | None = None
    max_steps: int | None = None
    overrides: dict[str, Any] = field(default_factory=dict)
    model_overrides: dict[str, Any] = field(default_factory=dict)
    progress: bool = True
    device: str | None = None
    command: str = ""
    init: str | None = None


@dataclass
class _Progress:
    step: int = 0
    best_val: float = math.inf
    best_step: int = -1
    bad_evals: int = 0
    history: list = field(default_factory=list)  # [step, train loss, validation loss]
    wall_time_s: float = 0.0
    finished: str = ""  # "max epochs" or "early stopping" once training is complete


def state_path(out: str | Path) -> Path:
    """Where the training state of checkpoint `out` lives."""
    return Path(str(out) + STATE_SUFFIX)


def train(opts: TrainOptions, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train (or resume training) a model; see the module docstring.

    Returns:
        Summary: "out", "stop_reason", "step", "best_step", "best_val_loss", "wall_time_s",
        "trajectories_per_s", "n_parameters".

    Raises:
        InputError: bad options, unusable data, an --out that holds another run, or another
            process training into the same --out.
        DatasetError: a corrupt dataset directory.
        CheckpointError: a corrupt training state.
    """
    ctx = init_distributed(opts.device)
    try:
        with exclusive(opts.out, ctx.is_main), StopOnSignal() as stop:
            return _Trainer(opts, ctx, log, stop).run()
    finally:
        shutdown_distributed()


class _Trainer:
    def __init__(self, opts: TrainOptions, ctx: DistContext, log: Callable[[str], None],
                 stop: StopOnSignal) -> None:
        self.opts, self.ctx, self.signals = opts, ctx, stop
        self.log = log if ctx.is_main else (lambda _: None)
        self.cfg, tcfg = preset(opts.preset, opts.representation, **opts.model_overrides)
        try:
            self.tcfg = tcfg.replace(**opts.overrides)
        except TypeError as exc:
            raise InputError("overrides", str(exc), opts.overrides) from exc
        if opts.max_minutes is not None and not opts.max_minutes > 0:
            raise InputError("--max-minutes", "must be > 0", opts.max_minutes)
        self.init = None if opts.init is None else _initial_model(opts.init, self.cfg)
        self.data = load_training_data(list(opts.data), opts.representation,
                                       self.tcfg.val_fraction, opts.seed,
                                       self.cfg.normalization, self.cfg.context,
                                       self.tcfg.max_train,
                                       None if self.init is None else self.init.normalizer,
                                       self.tcfg.dagger_max_cost_ratio,
                                       self.tcfg.dagger_reward)
        if self.init is not None:
            _check_init_data(opts.init, self.init, self.data.provenance)
        self.autocast = (self.tcfg.precision == "bf16" and ctx.device.type == "cuda")
        # (M,) first node inside the loss of each row, on the CPU: the loss counts of a step
        # come from the same mask as its batch without a device round trip
        self.train_from = self.data.tensors["train_from"].numpy().copy()
        if ctx.device.type == "cuda":  # keep the (small) dataset resident: batches are gathers
            self.data.tensors.update({k: v.to(ctx.device) for k, v in self.data.tensors.items()})
        if self.data.n_nodes > self.cfg.context:
            raise InputError("--data", f"trajectories of {self.data.n_nodes} nodes exceed the "
                             f"model's context K = {self.cfg.context}")
        torch.manual_seed(opts.seed)
        self.model = ArtModel(self.cfg).to(ctx.device)
        if self.init is not None:
            self.model.load_state_dict(self.init.model.state_dict())
        self.params = list(self.model.parameters())
        self.opt = torch.optim.AdamW(self.params, lr=self.tcfg.lr,
                                     weight_decay=self.tcfg.weight_decay)
        n_train = self.data.train_rows.size
        self.steps_per_epoch = math.ceil(n_train / self.tcfg.batch_size)
        self.total_steps = self.tcfg.max_epochs * self.steps_per_epoch
        self.eval_every = self.tcfg.eval_every or self.steps_per_epoch
        self.val_starts = validation_starts(opts.seed, self.data.val_rows.size,
                                            self.data.n_nodes, self.tcfg.suffix_fraction)
        self.prog = _Progress()
        self.best_state = _copy_state(self.model)
        self._order_cache: tuple[int, np.ndarray] = (-1, np.empty(0))
        self.fingerprint = self._fingerprint()
        self._resume()

    # ------------------------------------------------------------------ set-up
    def _fingerprint(self) -> str:
        what = {"preset": self.opts.preset, "model": self.cfg.to_dict(),
                "train": self.tcfg.to_dict(), "seed": self.opts.seed,
                "manifests": [m["manifest_sha256"] for m in self.data.provenance["manifests"]]}
        if self.init is not None:
            what["init_sha256"] = self.init.sha256
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()

    def _resume(self) -> None:
        path = state_path(self.opts.out)
        if not path.exists():
            if Path(self.opts.out).exists():
                raise InputError("--out", "exists but has no training state next to it "
                                 f"({path.name}); choose a new path or delete it", self.opts.out)
            if self.init is not None:  # the initial model is the best so far (step 0)
                val = self.validation_loss()
                self.prog.history.append([0, math.nan, val])
                self.prog.best_val, self.prog.best_step = val, 0
                self.log(f"initial model {Path(self.opts.init).name} (sha256 "
                         f"{self.init.sha256[:12]}): validation loss {val:.4g}")
            return
        payload, _ = checkpoint.read_payload(path)
        if payload.get("kind") != "train-state" or payload.get("fingerprint") != self.fingerprint:
            raise InputError("--out", f"{path} holds the state of a different training run "
                             "(data, preset, representation, seed or hyperparameters differ); "
                             "use a new --out or delete it", self.opts.out)
        model, _ = checkpoint.build(path, payload)
        self.model.load_state_dict(model.state_dict())
        self.best_state = {k: v.to(self.ctx.device) for k, v in
                           payload["best_state_dict"].items()}
        self.opt.load_state_dict(payload["optimizer"])
        self.prog = _Progress(**payload["progress"])
        self.log(f"resuming {self.opts.out} at step {self.prog.step} "
                 f"(best validation loss {self.prog.best_val:.4g} at step {self.prog.best_step})")

    # ------------------------------------------------------------------ loop
    def run(self) -> dict[str, Any]:
        if self.prog.finished:
            self.log(f"{self.opts.out}: training already finished ({self.prog.finished} at step "
                     f"{self.prog.step}); nothing to do")
            return self._summary()
        n_par = self.model.n_parameters()
        self.log(f"training {self.opts.preset} ({n_par / 1e6:.2f} M parameters, "
                 f"{self.opts.representation}) on {self.data.train_rows.size} trajectories, "
                 f"validating on {self.data.val_rows.size}; {self.steps_per_epoch} steps/epoch,"
                 f" batch {self.tcfg.batch_size}, {self.ctx.world_size} process(es) on "
                 f"{self.ctx.device}")
        t0, wall0, steps0 = time.perf_counter(), self.prog.wall_time_s, self.prog.step
        self._session = (t0, wall0, steps0)
        bar = tqdm(total=self.total_steps, initial=self.prog.step, unit="step", desc="train",
                   disable=not (self.opts.progress and self.ctx.is_main), dynamic_ncols=True)
        stop, losses = "", []
        while not stop:
            stop = self._limit_reached(t0)
            if stop:
                break
            losses.append(self._step())
            self.prog.wall_time_s = wall0 + time.perf_counter() - t0
            bar.update(1)
            last_val = self.prog.history[-1][2] if self.prog.history else math.nan
            bar.set_postfix(train=f"{np.mean(losses[-50:]):.4g}", val=f"{last_val:.4g}",
                            best=f"{self.prog.best_val:.4g}")
            if self.prog.step % self.eval_every == 0 or self.prog.step == self.total_steps:
                stop = self._evaluate(float(np.mean(losses)), bar)
                losses = []
        bar.close()
        if stop == "interrupted":  # at a step boundary: the state is exact, resume continues
            self._save()
            self.log(f"interrupted at step {self.prog.step}; the same command resumes")
            return dict(self._summary(), stop_reason=stop)
        if losses:  # stopped between validation passes (time or step limit)
            self._evaluate(float(np.mean(losses)), None)
        if stop in ("max epochs", "early stopping"):
            self.prog.finished = stop
        self._save()
        self.log(f"stopped at step {self.prog.step} ({stop}); best validation loss "
                 f"{self.prog.best_val:.4g} at step {self.prog.best_step} -> {self.opts.out}")
        return dict(self._summary(), stop_reason=stop)

    def _limit_reached(self, t0: float) -> str:
        if self.prog.step >= self.total_steps:
            return "max epochs"
        if self.opts.max_steps is not None and self.prog.step >= self.opts.max_steps:
            return "max steps"
        over = self.opts.max_minutes is not None and \
            time.perf_counter() - t0 > 60.0 * self.opts.max_minutes
        # every process stops at the same step, whichever of them got the signal
        interrupted, over = (v > 0 for v in self.ctx.sum([float(self.signals.requested),
                                                          float(over)]))
        return "interrupted" if interrupted else "time limit" if over else ""

    def _lr(self, step: int) -> float:
        t = self.tcfg
        if step < t.warmup_steps:
            return t.lr * (step + 1) / t.warmup_steps
        span = max(self.total_steps - t.warmup_steps, 1)
        cos = 0.5 * (1.0 + math.cos(math.pi * min((step - t.warmup_steps) / span, 1.0)))
        return t.lr * (t.min_lr_ratio + (1.0 - t.min_lr_ratio) * cos)

    def _rows(self, step: int) -> np.ndarray:
        epoch, k = divmod(step, self.steps_per_epoch)
        if self._order_cache[0] != epoch:
            self._order_cache = (epoch, epoch_order(self.opts.seed, epoch, self.data.train_rows))
        bs = self.tcfg.batch_size
        return self._order_cache[1][k * bs:(k + 1) * bs]

    def _step(self) -> float:
        step, n = self.prog.step, self.data.n_nodes
        rows = self._rows(step)
        starts = suffix_starts(self.opts.seed, step, rows.size, n, self.tcfg.suffix_fraction)
        counts = loss_counts(valid_mask(starts, n, self.train_from[rows]))
        mine = self.ctx.share(np.arange(rows.size))
        for group in self.opt.param_groups:
            group["lr"] = self._lr(step)
        seed = np.random.SeedSequence([self.opts.seed, step, self.ctx.rank]).generate_state(1)
        torch.manual_seed(int(seed[0]))  # dropout masks
        self.model.train()
        local = 0.0
        if mine.size:
            batch = make_batch(self.data.tensors, rows[mine], starts[mine], self.cfg.context,
                               self.ctx.device)
            with self._precision():
                sse_u, sse_x, bce = loss_terms(self.model, batch, self.tcfg.burn_threshold_mps)
            loss = combined_loss(sse_u, sse_x, bce, counts, self.tcfg.gate_weight)
            loss.backward()
            local = float(loss.detach())
        self.ctx.sum_gradients(self.params)
        torch.nn.utils.clip_grad_norm_(self.params, self.tcfg.grad_clip)
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        self.prog.step += 1
        return self.ctx.sum([local])[0]

    def validation_loss(self) -> float:
        """Loss of the current weights on the validation sequences (eval mode)."""
        rows, starts = self.data.val_rows, self.val_starts
        counts = loss_counts(valid_mask(starts, self.data.n_nodes, self.train_from[rows]))
        mine = self.ctx.share(np.arange(rows.size))
        sse = [0.0, 0.0, 0.0]
        self.model.eval()
        with torch.no_grad():
            for i in range(0, mine.size, self.tcfg.batch_size):
                sel = mine[i:i + self.tcfg.batch_size]
                batch = make_batch(self.data.tensors, rows[sel], starts[sel], self.cfg.context,
                                   self.ctx.device)
                with self._precision():
                    terms = loss_terms(self.model, batch, self.tcfg.burn_threshold_mps)
                for j, term in enumerate(terms):
                    sse[j] += float(term)
        total = self.ctx.sum(sse)
        return combined_loss(*total, counts, self.tcfg.gate_weight)

    def _precision(self) -> contextlib.AbstractContextManager:
        """bf16 autocast of the forward pass on CUDA when asked, else nothing."""
        if self.autocast:
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _evaluate(self, train_loss: float, bar: tqdm | None) -> str:
        val = self.validation_loss()
        p = self.prog
        p.history.append([p.step, train_loss, val])
        better = val < p.best_val
        if better:
            p.best_val, p.best_step, p.bad_evals = val, p.step, 0
            self.best_state = _copy_state(self.model)
        else:
            p.bad_evals += 1
        msg = (f"step {p.step} (epoch {p.step / self.steps_per_epoch:.2f}): train {train_loss:.4g}"
               f", validation {val:.4g}{' (best)' if better else ''}, lr {self._lr(p.step):.2g},"
               f" {self._rate():.1f} traj/s")
        if self.ctx.is_main:
            (bar.write if bar is not None else self.log)(msg)
        stop = "early stopping" if p.bad_evals >= self.tcfg.patience else ""
        self._save()
        return stop

    def _rate(self) -> float:
        t0, wall0, steps0 = self._session
        dt = time.perf_counter() - t0
        return (self.prog.step - steps0) * self.tcfg.batch_size / dt if dt > 0 else 0.0

    # ------------------------------------------------------------------ output
    def _meta(self) -> dict[str, Any]:
        p = self.prog
        return {"dataset": self.data.provenance, "training": {
            "command": self.opts.command, "preset": self.opts.preset, "seed": self.opts.seed,
            "representation": self.opts.representation, "train_config": self.tcfg.to_dict(),
            "step": p.step, "epoch": p.step / self.steps_per_epoch, "best_step": p.best_step,
            "best_val_loss": p.best_val, "history": p.history, "stop_reason": p.finished,
            "wall_time_s": p.wall_time_s, "trajectories_per_s": self._rate(),
            "world_size": self.ctx.world_size, "device": str(self.ctx.device),
            "threads": torch.get_num_threads(), "n_parameters": self.model.n_parameters(),
            "torch_version": str(torch.__version__), "art_guidance_version": __version__,
            "init": None if self.init is None else {
                "file": Path(self.opts.init).name, "sha256": self.init.sha256,
                "trained_on": list(trained_manifests(self.init.meta)),
                "seed_bases": list(trained_seed_bases(self.init.meta))}}}

    def _save(self) -> None:
        if self.ctx.is_main:
            meta = self._meta()
            state = checkpoint.model_payload(self.model, self.data.normalizer, meta)
            state.update(kind="train-state", fingerprint=self.fingerprint,
                         best_state_dict=_copy_state(self.model, self.best_state, cpu=True),
                         optimizer=self.opt.state_dict(),
                         progress=dataclasses.asdict(self.prog))
            checkpoint.save(state_path(self.opts.out), state)
            checkpoint.save(self.opts.out, checkpoint.model_payload(
                self.model, self.data.normalizer, meta, state_dict=self.best_state))
        self.ctx.barrier()

    def _summary(self) -> dict[str, Any]:
        p = self.prog
        return {"out": str(self.opts.out), "stop_reason": p.finished, "step": p.step,
                "best_step": p.best_step, "best_val_loss": p.best_val,
                "wall_time_s": p.wall_time_s,
                "trajectories_per_s": p.step * self.tcfg.batch_size / max(p.wall_time_s, 1e-9),
                "n_parameters": self.model.n_parameters()}


def _copy_state(model: ArtModel, state: dict[str, torch.Tensor] | None = None,
                cpu: bool = False) -> dict[str, torch.Tensor]:
    src = model.state_dict() if state is None else state
    return {k: (v.detach().cpu() if cpu else v.detach()).clone() for k, v in src.items()}
