"""The shipped models' catalogue (udh_cli.models_catalog) against what an installed package carries."""

from __future__ import annotations

import tomllib
from pathlib import Path

from udh_cli import models_catalog

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_run_is_installed_with_the_package():
    # A wheel carries only the files package-data names; a run's weights left out would make
    # `udh train --init unsupervised-flight` fail for everyone who did not install from a clone.
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["udh_cli.models"]
    for name, relative in models_catalog.SHIPPED_RUNS.items():
        assert relative in patterns, name
        assert (ROOT / "models" / relative).is_file(), name
        assert models_catalog.shipped_checkpoint(name) == models_catalog.models_dir() / relative
