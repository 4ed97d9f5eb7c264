"""Shared command-line pieces (vrs_jax.cli.common): program names, help text, formats."""

from __future__ import annotations

import sys

import pytest

from vrs_jax.cli import build_egm, demo, evaluate, localize, make_synthetic, train, train_nerf
from vrs_jax.cli.common import load_scene_from_args, prog
from vrs_jax.errors import VrsError

PARSERS = [build_egm.build_parser, demo.build_parser, evaluate.build_parser,
           localize.build_parser, make_synthetic.build_parser, train.build_parser,
           train_nerf.build_parser]


def test_program_name_is_the_console_script_when_run_as_one(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["/venv/bin/vrs-jax-localize", "--help"])
    assert prog("experiments.localize") == "vrs-jax-localize"
    assert localize.build_parser().format_usage().startswith("usage: vrs-jax-localize")
    monkeypatch.setattr(sys, "argv", ["/x/experiments/localize.py"])
    assert prog("experiments.localize") == "python -m experiments.localize"


@pytest.mark.parametrize("make", PARSERS)
def test_help_names_each_default_once_and_never_none(make):
    text = make().format_help()
    assert "(default: None)" not in text and "(default: False)" not in text
    assert "(default: [])" not in text
    for line in text.split("\n  -"):  # one option's help at a time
        assert line.count("(default") <= 1, line


def test_help_examples_keep_their_line_continuations():
    text = train_nerf.build_parser().format_help()
    assert "/data/lego \\\n        --query-every 8" in text


def test_unknown_format_lists_images_too():
    args = type("A", (), {"fmt": "7scene", "root": ".", "opt": [], "query_every": None,
                          "downscale": None})()
    with pytest.raises(VrsError, match=r"known: .*colmap, images"):
        load_scene_from_args(args)


def test_outdoor_entry_points_contract_the_far_field_by_default():
    """Cambridge and Aachen are unbounded: their training commands set contraction=true
    unless the user says otherwise (a later --set wins); 7Scenes (indoor) does not."""
    from vrs_jax.cli import train_aachen, train_cambridge
    from vrs_jax.cli.train import build_parser
    from vrs_jax.nerf.config import parse_overrides

    cam = train_cambridge.parser().parse_args(["--root", "r", "--scene", "s", "--out", "o"])
    assert parse_overrides(cam.set) == {"contraction": True}
    off = train_cambridge.parser().parse_args(["--root", "r", "--scene", "s", "--out", "o",
                                               "--set", "contraction=false"])
    assert parse_overrides(off.set) == {"contraction": False}
    aachen = train_aachen.parser().parse_args(["--root", "r", "--out", "o"])
    assert parse_overrides(aachen.set) == {"contraction": True} and aachen.clusters == 16
    seven = build_parser("7scenes").parse_args(["--root", "r", "--out", "o"])
    assert "contraction" not in parse_overrides(seven.set)
