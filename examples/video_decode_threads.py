"""Video decode with one FFmpeg thread (what udh's video reader asks for) against FFmpeg's default threads.

    python examples/video_decode_threads.py [--frames 100] [--frame-size 1600x1200] [--repeats 3]

Makes a video of a textured ground seen by a moving camera with ``cv2.VideoWriter`` (H.264 where this OpenCV
can encode it, else through PyAV when it is installed, else MPEG-4 Part 2), then decodes every frame in this one
process with ``CAP_PROP_N_THREADS`` 1 and with OpenCV's default, alternating, and prints the best wall and CPU
seconds of each. Why one thread in udh: FFmpeg's damage report then comes with the frame it smeared.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def flight_frames(count: int, width: int, height: int):
    """``count`` (height, width, 3) uint8 frames: a smooth random ground panned 6 px and 4 px a frame."""
    rng = np.random.default_rng(0)
    ground = cv2.resize(rng.integers(0, 256, ((height + 4 * count) // 3, (width + 6 * count) // 3, 3), dtype=np.uint8),
                        (width + 6 * count, height + 4 * count), interpolation=cv2.INTER_CUBIC)
    for number in range(count):
        yield np.ascontiguousarray(ground[4 * number:4 * number + height, 6 * number:6 * number + width])


def write_video(path: Path, count: int, width: int, height: int) -> str:
    """Write the flight to ``path``; returns the codec used."""
    if _write_with_opencv(path, "avc1", count, width, height):
        return "H.264 (cv2.VideoWriter avc1)"
    try:
        import av
    except ImportError:
        if _write_with_opencv(path, "mp4v", count, width, height):
            return "MPEG-4 Part 2 (cv2.VideoWriter mp4v; this OpenCV encodes no H.264 and PyAV is not installed)"
        raise SystemExit("this OpenCV can write no MP4 video") from None
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        for image in flight_frames(count, width, height):
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")))
        container.mux(stream.encode(None))
    return "H.264 (libx264 through PyAV: this OpenCV encodes no H.264)"


def _write_with_opencv(path: Path, fourcc: str, count: int, width: int, height: int) -> bool:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (width, height))
    if not writer.isOpened():
        return False
    for image in flight_frames(count, width, height):
        writer.write(image)
    writer.release()
    return True


def decode_all(path: Path, threads: int | None) -> tuple[float, float, int]:
    """(wall s, CPU s of this process, frames) to decode every frame; ``threads`` None keeps OpenCV's default."""
    params = [] if threads is None else [cv2.CAP_PROP_N_THREADS, threads]
    wall, cpu = time.perf_counter(), time.process_time()
    capture = cv2.VideoCapture(str(path), cv2.CAP_ANY, params)
    frames = 0
    while capture.read()[0]:
        frames += 1
    capture.release()
    return time.perf_counter() - wall, time.process_time() - cpu, frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--frame-size", default="1600x1200")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    width, height = (int(v) for v in args.frame_size.split("x"))
    with tempfile.TemporaryDirectory() as folder:
        video = Path(folder) / "flight.mp4"
        codec = write_video(video, args.frames, width, height)
        print(f"{args.frames} frames {width}x{height}, {codec}, {video.stat().st_size / 1e6:.1f} MB; {cv2.getNumberOfCPUs()} CPUs")
        runs: dict[str, list[tuple[float, float, int]]] = {"1 thread": [], "default": []}
        for _ in range(args.repeats):
            runs["1 thread"].append(decode_all(video, 1))
            runs["default"].append(decode_all(video, None))
    for name, results in runs.items():
        wall, cpu = min(r[0] for r in results), min(r[1] for r in results)
        print(f"{name:>9}: wall {wall:.2f} s ({1000 * wall / results[0][2]:.1f} ms a frame), CPU {cpu:.2f} s, {results[0][2]} frames")


if __name__ == "__main__":
    main()
