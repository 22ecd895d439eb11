"""Every `udh` command in the README runs from a fresh clone: a README example cannot rot."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PLACEHOLDERS = ("my_flight", "your_", "flight.mp4")  # commands about the reader's own data
# Exit codes the README promises for a command: a 20-step network answers unverified (3).
EXPECTED = {"--model try.onnx": 3}


def readme_commands() -> list[str]:
    """The `udh ...` lines of the README's bash blocks, backslash continuations joined, in order."""
    text = (REPO / "README.md").read_text()
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].strip()
            if line.startswith("udh ") and not any(p in line for p in PLACEHOLDERS):
                commands.append(line)
    return commands


def test_the_readme_has_an_example_for_every_command():
    verbs = {shlex.split(c)[1] for c in readme_commands()}
    assert {"estimate", "mosaic", "bench", "train", "export-onnx", "quantize"} <= verbs


@pytest.mark.slow
def test_every_readme_command_runs(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    for name in ("examples", "models"):
        (tmp_path / name).symlink_to(REPO / name)
    for command in readme_commands():
        args = shlex.split(command)[1:]
        result = subprocess.run([sys.executable, "-m", "udh_cli", *args], cwd=tmp_path, capture_output=True, text=True, timeout=600)
        expected = next((code for key, code in EXPECTED.items() if key in command), 0)
        assert result.returncode == expected, f"{command}\n{result.stderr[-2000:]}"
        assert "Traceback" not in result.stderr
