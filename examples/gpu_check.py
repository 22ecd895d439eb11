"""udh on an NVIDIA GPU against the same machine's CPU: a network pass, training steps and a mosaic, with the
answers compared.

    python examples/gpu_check.py --out gpu_check.json [--frames examples/sim_flight] [--train-steps 30]

Writes one JSON record and prints a table. Each figure is a median over repeats after a warm-up:

- **network pass**: the shipped coarse network (``models/udh-unsupervised.pt``) on (N, 2, 128, 128) patches, in
  torch on the GPU and in onnxruntime on the CPU (float32 ONNX export of the same weights), for N = 1 and 64; the
  largest difference between the two answers, in pixels at the corners;
- **onnxruntime providers**: which the installed onnxruntime offers; with ``CUDAExecutionProvider`` (the
  ``onnxruntime-gpu`` wheel) the ONNX network is timed on it too, and the mosaic below runs on it;
- **training**: seconds per ``udh train`` step of the unsupervised coarse network (batch 64) and of the matcher
  (batch 8, 192 px views), on the GPU and on the CPU, data generation included, as the command runs them;
- **mosaic**: ``udh mosaic`` of ``--frames`` with the default method, once on onnxruntime's CPU provider and, where
  the CUDA provider exists, once on it, with the largest corner difference between the two runs' homographies.

Without a GPU the script still runs (torch on the CPU stands in), so its test runs everywhere; the record says
which device each figure came from.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CHECKPOINT = REPO / "models" / "udh-unsupervised.pt"
ONNX_FP32 = REPO / "models" / "udh-unsupervised.onnx"


def _median_seconds(call, repeats: int) -> float:
    call()  # warm-up: kernels compiled, memory allocated
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _corner_px(offsets: np.ndarray) -> np.ndarray:
    """(N, 8) 4-point offsets -> (N,) largest corner displacement, px."""
    return np.linalg.norm(offsets.reshape(-1, 4, 2), axis=2).max(axis=1)


def network_pass(repeats: int) -> dict:
    import onnxruntime as ort
    import torch

    from udh_cli.train.archs import create_model
    from udh_cli.train.checkpoint import load_checkpoint

    state = load_checkpoint(CHECKPOINT)
    size = int(state["config"]["patch_size"])
    model = create_model(state["config"]["arch"], size).eval()
    model.load_state_dict(state["model"])
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    model = model.to(device)
    providers = ort.get_available_providers()
    sessions = {"CPUExecutionProvider": ort.InferenceSession(str(ONNX_FP32), providers=["CPUExecutionProvider"])}
    if "CUDAExecutionProvider" in providers:
        sessions["CUDAExecutionProvider"] = ort.InferenceSession(str(ONNX_FP32), providers=["CUDAExecutionProvider"])
    rng = np.random.default_rng(0)
    found: dict = {"torch_device": str(device), "gpu": torch.cuda.get_device_name(0) if device.type == "cuda" else None,
                   "onnxruntime": ort.__version__, "onnxruntime_providers": providers, "batches": {}}
    for batch in (1, 64):
        patches = rng.standard_normal((batch, 2, size, size)).astype(np.float32)
        tensor = torch.from_numpy(patches).to(device)

        def torch_pass():
            with torch.no_grad():
                out = model(tensor)
            if device.type == "cuda":
                torch.cuda.synchronize()
            return out

        row = {"torch_" + device.type + "_ms": 1e3 * _median_seconds(torch_pass, repeats)}
        reference = torch_pass().cpu().numpy()
        for name, session in sessions.items():
            row[f"onnxruntime_{name}_ms"] = 1e3 * _median_seconds(lambda s=session: s.run(None, {"patches": patches}), repeats)
            got = session.run(None, {"patches": patches})[0]
            row[f"max_corner_diff_px_{name}"] = float(_corner_px(got - reference).max())
        found["batches"][str(batch)] = row
    return found


def _train_seconds_per_step(args: list[str], steps: int, cuda: bool) -> float:
    """Seconds per step of a short ``udh train`` run (the first step, with its warm-up, left out)."""
    env = dict(os.environ)
    if not cuda:
        env["CUDA_VISIBLE_DEVICES"] = ""
    times = []
    with tempfile.TemporaryDirectory() as folder:
        for count in (1, 1 + steps):
            out = Path(folder) / f"run{count}"
            start = time.perf_counter()
            done = subprocess.run([sys.executable, "-m", "udh_cli.cli", "train", *args, "--steps", str(count), "--eval-every", "1000",
                                   "--out", str(out)], env=env, cwd=REPO, capture_output=True, text=True)
            if done.returncode != 0:
                raise RuntimeError(f"udh train failed on {'cuda' if cuda else 'cpu'}: {done.stderr.strip().splitlines()[-1:]}")
            times.append(time.perf_counter() - start)
    return (times[1] - times[0]) / steps


def training(steps: int, frames: Path) -> dict:
    import torch

    coarse = ["--data", str(frames), "--batch", "64", "--threads", "4"]
    matcher = ["--mode", "match", "--arch", "matcher", "--data", str(frames), "--motion", "flight", "--patch-size", "192", "--batch", "8",
               "--threads", "4"]
    found = {}
    for name, args in (("coarse_batch64", coarse), ("matcher_batch8", matcher)):
        found[name] = {}
        for cuda in (False, True) if torch.cuda.is_available() else (False,):
            try:
                found[name][f"{'cuda' if cuda else 'cpu'}_s_per_step"] = _train_seconds_per_step(args, steps, cuda)
            except RuntimeError as exc:  # recorded, so that the other figures still come back
                found[name][f"{'cuda' if cuda else 'cpu'}_error"] = str(exc)
    return found


def mosaic(frames: Path) -> dict:
    import onnxruntime as ort

    from udh_cli.mosaic import MosaicConfig, run_mosaic

    devices = ["cpu"] + (["cuda"] if "CUDAExecutionProvider" in ort.get_available_providers() else [])
    found, homographies = {}, {}
    with tempfile.TemporaryDirectory() as folder:
        for device in devices:
            out = Path(folder) / device / "m.png"
            out.parent.mkdir()
            config = MosaicConfig(method_options={"device": device}, workers=1)
            start = time.perf_counter()
            run_mosaic(frames, out, config)
            found[f"{device}_wall_s"] = time.perf_counter() - start
            sidecar = json.loads(out.with_suffix(".json").read_text())
            homographies[device] = {frame["file"]: np.array(frame["mosaic_from_frame"]) for frame in sidecar["frames"]
                                    if frame.get("mosaic_from_frame") is not None}
    if "cuda" in homographies:
        corners = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float).T
        diffs = []
        for name, h_cpu in homographies["cpu"].items():
            a, b = h_cpu @ corners, homographies["cuda"][name] @ corners
            diffs.append(float(np.abs(a[:2] / a[2] - b[:2] / b[2]).max()))
        found["max_corner_diff_px"] = max(diffs)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the JSON record to write")
    parser.add_argument("--frames", type=Path, default=REPO / "examples" / "sim_flight")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--train-steps", type=int, default=20, help="0 leaves training out")
    parser.add_argument("--no-mosaic", action="store_true")
    args = parser.parse_args()
    record = {"date": time.strftime("%Y-%m-%d"), "machine": platform.node(), "cpu_count": os.cpu_count()}
    parts = [("network", lambda: network_pass(args.repeats))]
    if not args.no_mosaic:
        parts.append(("mosaic", lambda: mosaic(args.frames)))
    if args.train_steps:
        parts.append(("training", lambda: training(args.train_steps, args.frames)))
    for name, measure in parts:  # the record is rewritten after each part, so a cut-off run keeps what it measured
        record[name] = measure()
        args.out.write_text(json.dumps(record, indent=2))
    print(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
