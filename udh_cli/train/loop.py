"""``udh train``: the training loop, with atomic checkpoints, exact resume and torchrun support."""

from __future__ import annotations

import json
import math
import os
import signal
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.generator_settings import MotionConfig
from udh_cli.synthetic import PairConfig
from udh_cli.train import losses
from udh_cli.train.archs import MATCHERS, create_model, widen_from
from udh_cli.train.config import DEFAULT_LR, DEFAULT_STEPS, PHOTOMETRIC_SPACES, TrainConfig
from udh_cli.train.checkpoint import load_checkpoint, save_checkpoint
from udh_cli.train.data import Batch, MatchData, match_view, open_data
from udh_cli.train.run_folder import check_fresh_out, lock_run_folder, logged_step
from udh_cli.train.warm_start import ENCODER_INITS, WIDENINGS, load_encoder, load_weights, resolve_init


def _distributed() -> tuple[int, int]:
    """(rank, world size) under torchrun, else (0, 1). Initialises the process group once."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        torch.distributed.init_process_group(backend)
    return torch.distributed.get_rank(), world


def _to_tensors(batch: Batch, device: torch.device) -> dict[str, torch.Tensor]:
    out = {
        "patches": torch.from_numpy(batch.patches).to(device),
        "context_a": torch.from_numpy(batch.context_a).to(device),
        "origin": torch.from_numpy(batch.origin).to(device),
        "clean_b": torch.from_numpy(batch.clean_b).to(device),
    }
    if batch.offsets is not None:
        out["offsets"] = torch.from_numpy(batch.offsets).to(device)
    return out


def _standardise(patches: torch.Tensor, normalization: dict[str, float]) -> torch.Tensor:
    return (patches - normalization["mean"]) / normalization["std"]


class Trainer:
    """One training run. ``run()`` trains to ``config.steps``, resuming from ``out/checkpoint.pt`` if asked."""

    def __init__(self, config: TrainConfig, resume: bool = False, threads: int | None = None, progress: bool = True,
                 overwrite: bool = False):
        if config.mode not in DEFAULT_LR:
            raise UdhError(f"unknown --mode '{config.mode}'; choose unsupervised, supervised or match")
        if threads is not None and threads < 1:
            raise UdhError(f"--threads {threads}: give a positive number of CPU threads, or leave it out for torch's choice")
        self.rank, self.world = _distributed()
        self.out = Path(config.out)
        self.checkpoint_path = self.out / "checkpoint.pt"
        self.metrics_path = self.out / "metrics.jsonl"
        self.progress = progress and self.rank == 0
        saved = None
        self.notes: list[str] = []
        if not resume and self.rank == 0 and not overwrite:
            check_fresh_out(self.out, overwrite)  # refused at once; with --overwrite the old run goes only once this one can start
        if resume:
            if not self.checkpoint_path.is_file():
                raise UdhError(f"--resume: no checkpoint at {self.checkpoint_path}; start without --resume or give the run's --out")
            saved = load_checkpoint(self.checkpoint_path)
            stored = saved["config"]
            try:
                # The stored run defines everything except how long to train and where the data lies now.
                steps = config.steps if config.steps is not None else stored["steps"]
                lr = stored["lr"]
                if config.lr is not None and config.lr != stored["lr"]:
                    # Lowering the rate is the advice after a diverged run, so a new --lr is honoured, and said.
                    self.notes.append(f"--lr {config.lr} replaces the run's {stored['lr']} from step {int(saved['step'])} on")
                    lr = config.lr
                config = replace(TrainConfig.from_dict(stored), steps=max(steps, int(saved["step"])), lr=lr, data=config.data or stored["data"],
                                 out=config.out)
            except (KeyError, TypeError, ValueError) as exc:  # a damaged or foreign config: one line, not a traceback
                raise UdhError(f"{self.checkpoint_path}: the run's stored settings are damaged ({type(exc).__name__}: {exc}); "
                               f"start a new run with --overwrite or another --out") from None
        elif config.steps is None:
            config = replace(config, steps=DEFAULT_STEPS)
        self.config = config
        _check_config(config, self.out)
        if threads:
            torch.set_num_threads(threads)
        import cv2

        cv2.setNumThreads(1)  # data generation runs between steps; torch owns the cores
        self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        if not config.data:
            raise UdhError("no --data given; name one or more folders of images or flights")
        pair_config = PairConfig(config.patch_size, config.rho, config.small_motion_fraction, config.illumination, config.occluders,
                                 config.motion)
        if config.mode == "match":
            self.data = MatchData([Path(d) for d in config.data], pair_config)
        else:
            self.data = open_data([Path(d) for d in config.data], config.data_kind, pair_config, config.real_fraction, config.source_side)
        if config.mode == "supervised" and not self.data.has_labels:
            raise UdhError("supervised training needs synthetic pairs from image pools; flights have no labels (use --mode unsupervised)")
        torch.manual_seed(config.seed)
        self.model = create_model(config.arch, config.patch_size).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.learning_rate(), betas=config.betas, eps=config.eps)
        self.rng = np.random.default_rng([config.seed, self.rank])
        self.step = 0
        self.elapsed_before = 0.0  # seconds of training before the checkpoint we resume from
        self._clock_start: float | None = None
        self.best_val = math.inf
        # The loss summed since the last evaluation and its steps, checkpointed: a resumed run logs the same mean.
        self.running_loss, self.running_steps = 0.0, 0
        if saved is not None:
            self._restore(saved)
        elif config.init:
            init = load_checkpoint(resolve_init(config.init))
            widening = (init["config"]["arch"], config.arch) in WIDENINGS
            encoder_only = (init["config"]["arch"], config.arch) in ENCODER_INITS
            if encoder_only:
                load_encoder(self.model, init, f"--init {config.init}")
            elif (init["config"]["arch"] != config.arch and not widening) or int(init["config"]["patch_size"]) != config.patch_size:
                raise UdhError(f"--init {config.init} is a {init['config']['arch']} network for {init['config']['patch_size']}px patches; "
                               f"pass --arch {init['config']['arch']}")
            elif widening:
                widen_from(self.model, init["model"])
            else:
                load_weights(self.model, init, f"--init {config.init}")
            # The network's weights only make sense with the normalisation they were trained with.
            self.normalization = dict(init["normalization"])
            self.trained_before = {"init": str(config.init), "init_steps": int(init["step"]), "init_data": init["config"]["data"]}
        else:
            self.normalization = self._measure_normalization()
            self.trained_before = {}
        self.teacher = self._load_teacher(config.teacher) if config.teacher else None
        if self.world > 1:
            self.model = torch.nn.parallel.DistributedDataParallel(self.model)
        self.validation = self.data.validation(config.val_pairs)
        self.real_validation = self.data.real_validation(config.val_pairs) if hasattr(self.data, "real_validation") else None
        if not resume and self.rank == 0 and overwrite:  # every setting, the data and --init checked: replace the old run
            check_fresh_out(self.out, overwrite)

    # ------------------------------------------------------------------------------------ state

    def _measure_normalization(self) -> dict[str, float]:
        """Global standardisation: the mean and std of training inputs, measured once, stored with the model."""
        sample = self.data.batch(np.random.default_rng(self.config.seed + 999), 256, unsupervised=False).patches
        return {"mean": float(sample.mean()), "std": float(sample.std() + 1e-6)}

    def _load_teacher(self, name: str) -> tuple[torch.nn.Module, dict[str, float]]:
        """The frozen network to distil from, with the normalisation it was trained with."""
        state = load_checkpoint(resolve_init(name))
        if int(state["config"]["patch_size"]) != self.config.patch_size:
            raise UdhError(f"--teacher {name} works on {state['config']['patch_size']}px patches, this run on {self.config.patch_size}px")
        teacher = create_model(state["config"]["arch"], self.config.patch_size).to(self.device)
        load_weights(teacher, state, f"--teacher {name}")
        teacher.eval().requires_grad_(False)
        return teacher, dict(state["normalization"])

    def _bare_model(self) -> torch.nn.Module:
        return self.model.module if hasattr(self.model, "module") else self.model

    def _state(self) -> dict[str, Any]:
        rng_states = [self.rng.bit_generator.state]
        if self.world > 1:
            rng_states = [None] * self.world
            torch.distributed.all_gather_object(rng_states, self.rng.bit_generator.state)
        return {
            "model": self._bare_model().state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "step": self.step,
            "config": asdict(self.config),
            "normalization": self.normalization,
            "rng_states": [json.dumps(s) for s in rng_states],
            "torch_rng": torch.get_rng_state(),
            "best_val": self.best_val,
            "running_loss": self.running_loss,
            "running_steps": self.running_steps,
            "elapsed_s": self._elapsed(),
            "trained_before": self.trained_before,
            "data_description": self.data.description,
        }

    def _elapsed(self) -> float:
        """Wall seconds of training so far, including the runs this one resumed."""
        return self.elapsed_before if self._clock_start is None else time.perf_counter() - self._clock_start

    def _restore(self, saved: dict[str, Any]) -> None:
        self.model.load_state_dict(saved["model"])
        self.optimizer.load_state_dict(saved["optimizer"])
        self.step = int(saved["step"])
        self.normalization = dict(saved["normalization"])
        states = saved.get("rng_states", [])
        if self.rank < len(states):
            self.rng.bit_generator.state = json.loads(states[self.rank])
        torch.set_rng_state(saved["torch_rng"])
        self.best_val = float(saved.get("best_val", math.inf))
        running_loss, running_steps = saved.get("running_loss", 0.0), saved.get("running_steps", 0)
        if isinstance(running_loss, float) and math.isfinite(running_loss) and isinstance(running_steps, int) and running_steps >= 0:
            self.running_loss, self.running_steps = running_loss, running_steps  # else not a sum to trust: it starts at zero
        self.elapsed_before = float(saved.get("elapsed_s", 0.0))
        self.trained_before = dict(saved.get("trained_before", {}))
        self._truncate_metrics(self.step)

    def _truncate_metrics(self, step: int) -> None:
        """Drop log lines written after the checkpoint we resume from: they will be written again."""
        if self.rank != 0 or not self.metrics_path.is_file():
            return
        kept = [line for line in self.metrics_path.read_text(errors="replace").splitlines() if logged_step(line) <= step]
        from udh_cli.images import atomic_write_bytes

        atomic_write_bytes(self.metrics_path, ("\n".join(kept) + "\n" if kept else "").encode())

    def save(self) -> None:
        state = self._state()  # every rank joins the gather
        if self.rank == 0:
            save_checkpoint(self.checkpoint_path, state)

    # --------------------------------------------------------------------------------- training

    def _learning_rate(self) -> float:
        """Cosine decay from lr to lr * lr_final_fraction over the run (recomputed, so resume is exact)."""
        c = self.config
        progress = min(1.0, self.step / max(1, c.steps))
        return c.learning_rate() * (c.lr_final_fraction + (1 - c.lr_final_fraction) * 0.5 * (1 + math.cos(math.pi * progress)))

    def _loss(self, tensors: dict[str, torch.Tensor], offsets: torch.Tensor) -> torch.Tensor:
        if self.config.mode == "match":  # ``offsets`` are the matcher's descriptors here
            truth = geometry.homography_from_offsets(tensors["offsets"].double(), *match_view(self.config.patch_size))
            return losses.match_loss(offsets, truth, self._bare_model().log_temperature)
        if self.config.mode == "supervised":
            return losses.supervised_loss(offsets, tensors["offsets"])
        loss = losses.photometric_loss(offsets, tensors["context_a"], tensors["origin"], tensors["clean_b"],
                                       space=self.config.photometric)
        if self.teacher is not None:
            teacher, normalization = self.teacher
            with torch.no_grad():
                target = teacher(_standardise(tensors["patches"], normalization))
            loss = loss + self.config.teacher_weight * losses.distillation_loss(offsets, target)
        return loss

    @torch.no_grad()
    def evaluate(self) -> dict[str, float]:
        """Corner error on the fixed held-out set (MACE against the labels or the SIFT references); with
        mixed data also on the flights' held-out pairs, as ``val_real_*``."""
        found: dict[str, float] = {}
        if self.config.mode == "match":
            return self._evaluate_matcher()
        for prefix, batch in (("val", self.validation), ("val_real", self.real_validation)):
            if batch is None:
                continue
            model = self._bare_model()
            model.eval()
            tensors = _to_tensors(batch, self.device)
            predicted = torch.cat([model(_standardise(chunk, self.normalization)) for chunk in tensors["patches"].split(128)])
            model.train()
            errors = losses.corner_error(predicted, tensors["offsets"]).cpu().numpy()
            identity = losses.corner_error(torch.zeros_like(tensors["offsets"]), tensors["offsets"]).cpu().numpy()
            found.update({f"{prefix}_mace_mean": float(errors.mean()), f"{prefix}_mace_median": float(np.median(errors)),
                          f"{prefix}_mace_p95": float(np.percentile(errors, 95)), f"{prefix}_identity_median": float(np.median(identity))})
        return found

    def _evaluate_matcher(self) -> dict[str, float]:
        """Corner error of the homography that the estimator's own matching (mutual nearest cells, a robust
        fit; :mod:`udh_cli.estimators.matching`) finds from the descriptors, on the held-out views; a pair
        without an answer counts as the identity."""
        from udh_cli.estimators import matching

        model = self._bare_model()
        model.eval()
        tensors = _to_tensors(self.validation, self.device)
        width, height = match_view(self.config.patch_size)
        errors, identity, matched = [], [], []
        for patches, offsets in zip(tensors["patches"].split(32), tensors["offsets"].split(32)):
            described = model(_standardise(patches, self.normalization)).cpu().numpy()
            truths = geometry.homography_from_offsets(offsets.double().cpu().numpy(), width, height)
            for (feat_a, feat_b), truth in zip(described, truths):
                points_a, points_b, _ = matching.mutual_matches(feat_a, feat_b)
                found, inliers = matching.fit_matches(points_a, points_b)
                errors.append(float(geometry.mace(found if found is not None else np.eye(3), truth, width, height)))
                identity.append(float(geometry.mace(np.eye(3), truth, width, height)))
                matched.append(int(inliers.sum()))
        model.train()
        errors_array = np.array(errors)
        return {"val_mace_mean": float(errors_array.mean()), "val_mace_median": float(np.median(errors_array)),
                "val_mace_p95": float(np.percentile(errors_array, 95)), "val_identity_median": float(np.median(identity)),
                "val_fail_10px": float(np.mean(errors_array > 10)), "val_inliers_median": float(np.median(matched))}

    def _log(self, record: dict[str, Any]) -> None:
        if self.rank != 0:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        with self.metrics_path.open("a") as handle:
            handle.write(json.dumps(record) + "\n")

    def run(self) -> dict[str, Any]:
        """Train until ``config.steps``; returns the last metrics. Ctrl-C/SIGTERM save a checkpoint first."""
        c = self.config
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            from udh_cli.files import write_output

            # Checked before the run starts (check_fresh_out); recorded so that a later run knows it as udh's.
            write_output(self.out / "config.json", json.dumps(asdict(c), indent=2).encode(), overwrite=True)
        # SIGTERM and Ctrl-C ask the loop to stop at the next step boundary, after that step's validation,
        # log line and a checkpoint: saving mid-step would record a half-done step and resume inexactly.
        # A second signal stops at once, from the last checkpoint (as SIGKILL would).
        self._stop_requested = False
        previous = {sig: signal.signal(sig, self._request_stop) for sig in (signal.SIGTERM, signal.SIGINT)} if self.rank == 0 else {}
        last: dict[str, Any] = {}
        lock = lock_run_folder(self.out) if self.rank == 0 else None
        try:
            if self.step == 0 and self.validation is not None:
                last = {"step": 0, **self.evaluate(), "time_s": 0.0}
                self._log(last)
            last = self._train_steps(last)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            if lock is not None:
                lock.close()
        return last

    def _request_stop(self, signum, frame) -> None:  # noqa: ARG002 - signal handler signature
        if self._stop_requested:
            raise KeyboardInterrupt
        self._stop_requested = True

    def _train_steps(self, last: dict[str, Any]) -> dict[str, Any]:
        c = self.config
        from udh_cli.train.progress import TrainProgress

        # time_s in the log is wall time spent training this run, summed over every resume.
        self._clock_start = time.perf_counter() - self.elapsed_before
        self.model.train()
        with TrainProgress(c.steps, self.step, enabled=self.progress) as bar:
            while self.step < c.steps:
                batch = self.data.batch(self.rng, c.batch, unsupervised=c.mode == "unsupervised")
                tensors = _to_tensors(batch, self.device)
                for group in self.optimizer.param_groups:
                    group["lr"] = self._learning_rate()
                try:
                    offsets = self.model(_standardise(tensors["patches"], self.normalization))
                    loss = self._loss(tensors, offsets)
                except torch.linalg.LinAlgError:  # a diverged network's corners fall on a line: the DLT is singular
                    loss = torch.tensor(float("nan"))
                if not torch.isfinite(loss):
                    self._diverged(f"the loss became {loss.item()}")
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.step()
                if not all(torch.isfinite(p).all() for p in self.model.parameters()):
                    self._diverged("the weights became NaN or infinite")
                self.step += 1
                self.running_loss += float(loss.detach())
                self.running_steps += 1
                if self.step % c.eval_every == 0 or self.step == c.steps:
                    last = {"step": self.step, "loss": self.running_loss / self.running_steps, "lr": self._learning_rate(),
                            **self.evaluate(), "time_s": round(self._elapsed(), 1)}
                    self.running_loss, self.running_steps = 0.0, 0
                    self._log(last)
                    if last.get("val_mace_mean", math.inf) < self.best_val and self.rank == 0:
                        self.best_val = last["val_mace_mean"]
                        save_checkpoint(self.out / "best.pt", {**self._model_only_state(), "step": self.step})
                if self.step % c.checkpoint_every == 0 or self.step == c.steps or self._stop_requested:
                    self.save()
                bar.update(self.step, float(loss.detach()), last.get("val_mace_median"))
                if self._stop_requested and self.step < c.steps:
                    raise KeyboardInterrupt
        return last

    def _diverged(self, what: str) -> None:
        raise UdhError(f"{what} at step {self.step + 1}; the last good checkpoint {self.checkpoint_path} is kept: "
                       f"continue with --resume and a lower --lr")

    def _model_only_state(self) -> dict[str, Any]:
        return {"model": self._bare_model().state_dict(), "config": asdict(self.config), "normalization": self.normalization,
                "trained_before": self.trained_before, "data_description": self.data.description, "best_val": self.best_val}


def _check_config(config: TrainConfig, out: Path) -> None:
    """Refuse settings that cannot train, and an output folder that cannot be written, before any work."""
    if (config.mode == "match") != (config.arch in MATCHERS):
        raise UdhError(f"--mode {config.mode} and --arch {config.arch} do not go together: --mode match trains "
                       f"--arch {', '.join(sorted(MATCHERS))}, and only it")
    if config.mode == "match" and config.teacher:
        raise UdhError("--teacher distils a regressing network's offsets; --mode match has none")
    for name in ("steps", "batch", "eval_every", "checkpoint_every", "val_pairs", "patch_size"):
        if getattr(config, name) < 1:
            raise UdhError(f"--{name.replace('_', '-')} {getattr(config, name)}: must be at least 1")
    if config.teacher and not config.teacher_weight > 0:
        raise UdhError(f"--teacher-weight {config.teacher_weight}: must be positive when distilling from --teacher")
    if config.teacher and config.mode != "unsupervised":
        raise UdhError("--teacher distils without labels; it needs --mode unsupervised (supervised training has the true labels)")
    if not (config.rho > 0 and math.isfinite(config.rho)):
        raise UdhError(f"--rho {config.rho}: must be positive and finite")
    if config.lr is not None and not (config.lr > 0 and math.isfinite(config.lr)):
        raise UdhError(f"--lr {config.lr}: the learning rate must be positive and finite (the paper's: 1e-4 unsupervised, 5e-4 supervised)")
    if config.source_side and not 320 <= config.source_side <= 8000:
        raise UdhError(f"--source-side {config.source_side}: give 0 (the paper's 320x240) or a side from 320 to 8000 px")
    if not 0.0 <= config.real_fraction <= 1.0:
        raise UdhError(f"--real-fraction {config.real_fraction}: give a share of each batch from 0 to 1")
    if not 0.0 <= config.small_motion_fraction <= 1.0:
        raise UdhError(f"--small-motion {config.small_motion_fraction}: give a share of pairs from 0 to 1")
    if not 0.0 <= float(config.occluders) <= 1.0:
        raise UdhError(f"--occluders {config.occluders}: give a share of pairs from 0 to 1")
    motion = config.motion
    if motion is not None and not isinstance(motion, MotionConfig):
        raise UdhError(f"motion takes the flight motion (udh_cli.train.config.flight_motion) or None for the paper's, not {motion!r}")
    if config.photometric not in PHOTOMETRIC_SPACES:
        raise UdhError(f"--photometric {config.photometric}: choose one of {', '.join(PHOTOMETRIC_SPACES)}")
    if motion is not None and not (0 <= motion.max_heading <= 180 and 1 <= motion.scale_range[1] <= 4 and 0 <= motion.max_shift <= 1
                                   and 0.05 <= motion.min_overlap <= 1):
        raise UdhError(f"flight motion out of range: --max-heading {motion.max_heading} (0-180 degrees), "
                       f"--max-scale {motion.scale_range[1]} (1-4), --max-shift {motion.max_shift} (0-1 of the frame), "
                       f"--min-overlap {motion.min_overlap} (0.05-1)")
    if motion is not None and not 0.0 <= motion.residual <= config.patch_size / 4:
        raise UdhError(f"--residual {motion.residual}: give 0 (a first round) or a corner error up to {config.patch_size // 4} px")
    if out.exists() and not out.is_dir():
        raise UdhError(f"--out {out}: is a file; give a folder for the run")
    # Nothing is created until training starts, so a bad --data leaves no empty run folder behind.
    existing = next(p for p in [out, *out.absolute().parents] if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK):
        raise UdhError(f"--out {out}: {existing} is not a writable folder; choose another path")


def train(config: TrainConfig, resume: bool = False, threads: int | None = None, progress: bool = True,
          overwrite: bool = False, on_note: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Library entry point of ``udh train``: returns the final metrics record. ``on_note`` is told, before
    training starts, what the run changes of the user's request (a new --lr on resume)."""
    trainer = Trainer(config, resume=resume, threads=threads, progress=progress, overwrite=overwrite)
    for note in trainer.notes:
        if on_note is not None:
            on_note(note)
    last = trainer.run()
    if torch.distributed.is_initialized():
        # Every rank leaves together: once in CI, under load, a gloo rank aborted (SIGABRT) when its peer,
        # rank 0, which hosts the rendezvous store, had already exited.
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
    return last
