"""Packaging: the wheel installs vrs_jax only; every console script names a real main()."""

from __future__ import annotations

import importlib
from pathlib import Path

import tomllib
from setuptools import find_packages

ROOT = Path(__file__).resolve().parents[1]


def test_only_vrs_jax_is_installed():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    include = cfg["tool"]["setuptools"]["packages"]["find"]["include"]
    pkgs = find_packages(str(ROOT), include=include)
    assert pkgs and all(p == "vrs_jax" or p.startswith("vrs_jax.") for p in pkgs)
    assert "vrs_jax.cli" in pkgs


def test_console_scripts_and_experiment_wrappers():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    scripts = cfg["project"]["scripts"]
    for target in scripts.values():
        mod, fn = target.split(":")
        assert mod == "vrs_jax.cli.scripts", target  # imports its command behind a handler
        assert callable(getattr(importlib.import_module(mod), fn)), target
    # every CLI module has its console script and its `python -m experiments.NAME` wrapper
    cli = sorted(p.stem for p in (ROOT / "vrs_jax" / "cli").glob("*.py")
                 if p.stem not in ("__init__", "common", "scripts"))
    assert sorted(t.split(":")[1] for t in scripts.values()) == cli
    assert all(f"vrs-jax-{n.replace('_', '-')}" in scripts for n in cli)
    for name in cli:
        wrapper = importlib.import_module(f"experiments.{name}")
        assert wrapper.main is importlib.import_module(f"vrs_jax.cli.{name}").main
