"""The installed console scripts (``vrs-jax-NAME``, pyproject.toml): each imports its command
module only once a Ctrl-C handler is in place, so a Ctrl-C during the seconds the imports
take (jax) ends with one line and status 130, as ``python -m experiments.NAME`` does
(:func:`vrs_jax.errors.program_main`), not with a traceback through the imports."""

from __future__ import annotations

from collections.abc import Callable

from vrs_jax.errors import program_main


def _command(name: str) -> Callable[[], int]:
    def run() -> int:
        return program_main(f"vrs_jax.cli.{name}", "__main__")()

    run.__name__ = name
    run.__doc__ = f"The ``vrs-jax-{name.replace('_', '-')}`` console script."
    return run


train = _command("train")
train_7scenes = _command("train_7scenes")
train_cambridge = _command("train_cambridge")
train_aachen = _command("train_aachen")
train_nerf = _command("train_nerf")
build_egm = _command("build_egm")
localize = _command("localize")
evaluate = _command("evaluate")
make_synthetic = _command("make_synthetic")
demo = _command("demo")
